"""Figures as files: drawn by Agg outside pyplot, titles wrapped to fit, written atomically as PNG and SVG, and one
colour per model in every figure and render (the report's figures, its renders and the diagnosis' figures)."""

from __future__ import annotations

import textwrap
import zlib
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

# One colour per model in every figure and render, whichever models a sweep holds; grey is the ground truth's.
MODEL_COLOURS = {
    "mujoco_default": "tab:blue",
    "mujoco_fixed": "tab:orange",
    "sysid": "tab:green",
    "sysid_mjx": "yellowgreen",
    "gnn": "tab:red",
    "gnn_paper": "tab:purple",
    "hybrid": "tab:brown",
    "residual": "tab:pink",
    "bullet_default": "tab:olive",
    "sysid_bullet": "tab:cyan",
    "drake_default": "navy",
    "sysid_drake": "darkgoldenrod",
}
TRUTH_COLOUR = "0.6"
# Other models (a user's own): a colour picked by the name's checksum, the same in every figure and every run.
EXTRA_COLOURS = ("teal", "crimson", "indigo", "darkkhaki", "sienna", "slateblue", "seagreen", "orchid")


def model_colour(model: str) -> str:
    return MODEL_COLOURS.get(model) or EXTRA_COLOURS[zlib.crc32(model.encode()) % len(EXTRA_COLOURS)]


def new_figure(**kwargs) -> Figure:
    """A figure drawn by Agg into files only. Made outside pyplot, so no backend is selected, no display is needed
    (CI, a cluster node) and nothing global changes: the figure is freed like any object. Constrained layout makes
    room for every title, label and legend inside the figure."""
    figure = Figure(layout="constrained", **kwargs)
    FigureCanvasAgg(figure)
    return figure


def titles(figure: Figure) -> list:
    """The figure's title and every axes' titles that hold text."""
    found = [figure._suptitle] + [
        title for axis in figure.axes for title in (axis.title, axis._left_title, axis._right_title)
    ]
    return [title for title in found if title is not None and title.get_text()]


def wrap_titles(figure: Figure) -> None:
    """Break every title wider than what it stands over (the figure, or its axes) into lines that fit: layout can
    move a title down but cannot make a long one narrower."""
    renderer = figure.canvas.get_renderer()
    for title in titles(figure):
        room = figure.bbox.width if title is figure._suptitle else title.axes.bbox.width
        room = min(room, figure.bbox.width) * 0.96
        text = title.get_text().replace("\n", " ")
        width = title.get_window_extent(renderer).width
        if width <= room:
            continue
        columns = max(10, int(len(text) * room / width))
        while columns > 10:
            title.set_text("\n".join(textwrap.wrap(text, columns)))
            if title.get_window_extent(renderer).width <= room:
                break
            columns -= 2


def save_figure(figure: Figure, path: Path) -> Path:
    """Write a figure atomically, as PNG (path) and as SVG beside it (for papers), its titles wrapped to fit."""
    wrap_titles(figure)
    path.parent.mkdir(parents=True, exist_ok=True)
    for target in (path, path.with_suffix(".svg")):
        partial = target.with_name(f".{target.name}.partial{target.suffix}")
        figure.savefig(partial, dpi=110, metadata={"Date": None} if target.suffix == ".svg" else None)
        partial.replace(target)
    return path
