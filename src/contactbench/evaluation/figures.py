"""The paper's figures (1, 2, 3, 5, 7a-c) and Table 3, drawn from the metrics.json / per_trajectory.csv of test runs."""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D

from contactbench import variants as named_variants
from contactbench.evaluation.plotting import TRUTH_COLOUR, model_colour, new_figure, save_figure

# dataset -> (varied parameter, figure title as in the paper)
SWEEPS = {
    "bouncycubes": ("restitution", "Fig. 1: effect of restitution (BOUNCYCUBES)"),
    "frictioncubes": ("friction", "Fig. 2: effect of friction (FRICTIONCUBES)"),
    "polyhedra": ("faces", "Fig. 3: effect of geometry (POLYHEDRA)"),
    "multicubes": ("bodies", "Fig. 5: effect of the number of bodies (MULTICUBES)"),
}
# Table 3's dimensions: the paper's sweeps, and the future-work families' (named, not numbered, variants: no figure)
DIMENSIONS = {
    **{dataset: parameter for dataset, (parameter, _) in SWEEPS.items()},
    "nonconvex": "shape",
    "terrain": "ground and solid",
    "articulated": "joint_damping",
}
PANELS = [
    ("pos_err", "position error (widths)"),
    ("rot_err_rad", "rotation error (rad)"),
    ("floor_penetration_m", "floor penetration (mm)"),
]
# Metrics stored in m, drawn in mm (as the results table shows them).
MILLIMETRES = {"floor_penetration_m", "interbody_penetration_m", "min_vertex_height_m"}


def _unit(key: str) -> float:
    return 1e3 if key in MILLIMETRES else 1.0


# The error-over-time curves are means over the tosses still running at a frame; under this fraction of the split's
# tosses a mean is of a few tosses and swings, so it is drawn faint and grey instead.
RUNNING_FRACTION = 0.25


# Table 3's rule: a dimension matters for a method when its mean test position error moves by more than this
# fraction of its smallest value across the dimension's variants (and, with several seeds, by more than their spread).
IMPORTANCE_THRESHOLD = 0.25


@dataclass
class Run:
    summary: dict  # metrics.json
    per_trajectory: dict[str, np.ndarray]  # per_trajectory.csv columns
    path: Path | None = None  # the metrics.json

    @property
    def value(self) -> float:
        """The varied parameter's value: metrics.json's variant_values, or (older files) the variant's name."""
        values = self.summary.get("variant_values") or {}
        if len(values) == 1:
            return float(next(iter(values.values())))
        return float(self.summary["variant"].split("=", 1)[1])


@dataclass(frozen=True)
class Spread:
    """One metric of a cell, the runs that differ only by seed: the mean over the seeds and their min-max range."""

    mean: float
    low: float
    high: float
    n: int

    @classmethod
    def of(cls, values) -> Spread:
        values = np.asarray(values, dtype=float)
        return cls(float(values.mean()), float(values.min()), float(values.max()), len(values))

    @property
    def width(self) -> float:
        return self.high - self.low

    def overlaps(self, other: Spread) -> bool:
        return self.low <= other.high and other.low <= self.high


def seed_cells(runs: list[Run], key) -> list[list[Run]]:
    """Runs with the same key(run) that differ only by seed, together (cells in the order of their keys): one run
    per seed, the last found for it (metrics.json written before the seed was recorded count as one seed)."""
    cells: dict = {}
    for run in runs:
        cells.setdefault(key(run), {})[run.summary.get("seed")] = run
    return [list(cells[cell].values()) for cell in sorted(cells)]


# How a dataset was observed (contactbench/observation.py): the sensitivity study's two axes and their plain values.
OBSERVATION_AXES = {"noise_mm": ("tracking noise (mm)", 0.0), "frame_stride": ("frame stride (x dt)", 1)}


def observed_plainly(summary: dict) -> bool:
    """A run on the recordings as they are (every other figure and table is about these)."""
    return all(summary.get(axis, plain) == plain for axis, (_, plain) in OBSERVATION_AXES.items())


def load_test_runs(root: Path) -> list[Run]:
    runs = []
    for path in sorted(Path(root).rglob("metrics.json")):
        summary = json.loads(path.read_text())
        if summary.get("split") != "test":
            continue
        with open(path.parent / "per_trajectory.csv", newline="") as handle:
            rows = list(csv.DictReader(handle))
        columns = {name: np.array([float(row[name]) if row[name] else np.nan for row in rows]) for name in rows[0]}
        runs.append(Run(summary, columns, path))
    return runs


def _by_model(runs: list[Run], dataset: str) -> dict[str, list[list[Run]]]:
    """A dataset's runs per method: a cell per variant (its runs over seeds), in the order of the varied value."""
    grouped: dict[str, list[list[Run]]] = {}
    chosen = [run for run in runs if run.summary["dataset"] == dataset]
    for cell in seed_cells(chosen, lambda run: (run.summary["model"], run.value, run.summary["variant"])):
        grouped.setdefault(cell[0].summary["model"], []).append(cell)
    return grouped


def _plot_cells(axis, x: list[float], cells: list[list[Run]], key: str, label: str) -> None:
    """One method's line over x: the mean over each cell's seeds, the 25-75% band across the test trajectories of all
    its seeds, and with several seeds error bars from the lowest to the highest seed."""
    unit = _unit(key)
    spreads = [Spread.of([run.summary[key] * unit for run in cell]) for cell in cells]
    means = np.array([spread.mean for spread in spreads])
    (line,) = axis.plot(x, means, marker="o", label=label, color=model_colour(label))
    tosses = [np.concatenate([run.per_trajectory[key] for run in cell]) for cell in cells]
    low, high = zip(*(np.nanpercentile(values, [25, 75]) * unit for values in tosses))
    axis.fill_between(x, low, high, alpha=0.15, color=line.get_color())
    if any(spread.n > 1 for spread in spreads):
        lows, highs = np.array([[spread.low, spread.high] for spread in spreads]).T
        reach = np.clip([means - lows, highs - means], 0, None)  # equal seeds' mean can round a hair past them
        axis.errorbar(x, means, yerr=reach, fmt="none", capsize=3, color=line.get_color())


def _per_frame(run: Run, key: str) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in run.summary["per_frame"][key]], dtype=float)


def running_enough(cell: list[Run]) -> np.ndarray:
    """Per frame, whether at least RUNNING_FRACTION of the tosses are still running in every seed of the cell (all
    frames where metrics.json does not count them)."""
    enough = None
    for run in cell:
        counts = run.summary["per_frame"].get("n_trajectories")
        if counts is None:
            return np.ones(len(_per_frame(run, "pos_err")), dtype=bool)
        counts = np.array([0 if c is None else c for c in counts], dtype=float)
        ours = counts >= RUNNING_FRACTION * max(run.summary["n_trajectories"], 1)
        enough = ours if enough is None else enough & ours
    return enough


def _plot_curve(axis, cell: list[Run], key: str, only: np.ndarray | None = None, **style) -> None:
    """A per-frame curve: the mean over the cell's seeds, and with several seeds a band from their min to their max;
    with `only`, the frames outside it as a faint grey line beside the curve."""
    curves = np.array([_per_frame(run, key) for run in cell]) * _unit(key)
    mean = curves.mean(axis=0)
    frames = np.arange(curves.shape[1])
    shown = np.ones(len(mean), dtype=bool) if only is None else only
    (line,) = axis.plot(frames, np.where(shown, mean, np.nan), **style)
    if not shown.all():
        faint = ~shown
        faint[:-1] |= faint[1:]  # from the last frame drawn on, so the grey line continues the curve
        axis.plot(frames, np.where(faint, mean, np.nan), color=TRUTH_COLOUR, linewidth=0.8, alpha=0.6)
    if len(cell) > 1:
        low, high = np.where(shown, curves.min(axis=0), np.nan), np.where(shown, curves.max(axis=0), np.nan)
        axis.fill_between(frames, low, high, alpha=0.2, color=line.get_color())


def sweep_figure(runs: list[Run], dataset: str, path: Path) -> Path | None:
    """Mean per method against the varied parameter, with the 25-75% band across test trajectories and, with
    several seeds, the seeds' min-max as error bars."""
    grouped = _by_model(runs, dataset)
    if not grouped:
        return None
    parameter, title = SWEEPS[dataset]
    figure = new_figure(figsize=(4.2 * len(PANELS), 3.4))
    axes = figure.subplots(1, len(PANELS))
    for axis, (key, label) in zip(axes, PANELS):
        for model, cells in grouped.items():
            _plot_cells(axis, [cell[0].value for cell in cells], cells, key, model)
        axis.grid(True, alpha=0.3)
        axis.set_xlabel(parameter)
        axis.set_ylabel(label)
    axes[0].legend(fontsize=8)
    figure.suptitle(title)
    return save_figure(figure, path)


def per_frame_figure(
    runs: list[Run], dataset: str, key: str, label: str, title: str, path: Path, values: list[float] | None = None
) -> Path | None:
    """Per-frame curves (Fig. 7a: inter-body penetration, 7c: lowest vertex height) per method and variant, the
    mean over seeds with their min-max band."""
    chosen = [run for run in runs if run.summary["dataset"] == dataset and key in run.summary["per_frame"]]
    chosen = [run for run in chosen if values is None or run.value in values]
    if not chosen:
        return None
    figure = new_figure(figsize=(6, 3.6))
    axis = figure.subplots()
    variants = sorted({run.summary["variant"] for run in chosen}, key=_variant_order)
    for cell in seed_cells(chosen, lambda run: (run.summary["model"], run.value, run.summary["variant"])):
        model, variant = cell[0].summary["model"], cell[0].summary["variant"]
        dashes = ("-", "--", ":", "-.")[variants.index(variant) % 4]  # colour says the model, the dashes the variant
        _plot_curve(axis, cell, key, label=f"{model} {variant}", color=model_colour(model), linestyle=dashes)
    axis.set_xlabel("frame")
    axis.set_ylabel(label)
    axis.legend(fontsize=7)
    axis.set_title(title)
    return save_figure(figure, path)


def error_over_time_figure(runs: list[Run], dataset: str, path: Path) -> Path | None:
    """Position and rotation error against the frame, one column per variant, a line per method (test split; the
    mean over seeds with their min-max band), drawn only where at least RUNNING_FRACTION of the tosses still run
    (past that, a faint grey line)."""
    chosen = [run for run in runs if run.summary["dataset"] == dataset]
    if not chosen:
        return None
    variants = sorted({run.summary["variant"] for run in chosen}, key=_variant_order)
    figure = new_figure(figsize=(3.2 * len(variants) + 1.6, 6.0))
    axes = figure.subplots(2, len(variants), squeeze=False, sharey="row")
    greyed = False
    for column, variant in enumerate(variants):
        in_variant = [run for run in chosen if run.summary["variant"] == variant]
        for cell in seed_cells(in_variant, lambda run: run.summary["model"]):
            model = cell[0].summary["model"]
            enough = running_enough(cell)
            greyed = greyed or not enough[np.isfinite(_per_frame(cell[0], "pos_err"))].all()
            for row, key in enumerate(("pos_err", "rot_err_rad")):
                _plot_curve(axes[row, column], cell, key, only=enough, color=model_colour(model), label=model)
        axes[0, column].set_title(named_variants.label(dataset, variant), fontsize=9)
        axes[1, column].set_xlabel("frame")
        for axis in axes[:, column]:
            axis.grid(True, alpha=0.3)
    axes[0, 0].set_ylabel("position error (widths)")
    axes[1, 0].set_ylabel("rotation error (rad)")
    handles, labels = axes[0, -1].get_legend_handles_labels()
    if greyed:
        handles.append(Line2D([], [], color=TRUTH_COLOUR, linewidth=0.8, alpha=0.6))
        labels.append(f"< {RUNNING_FRACTION:.0%} of tosses running")
    axes[0, -1].legend(handles, labels, fontsize=7)
    figure.suptitle(
        f"Error over time, {dataset} (test): the mean over the tosses still running at each frame, "
        f"grey where fewer than {RUNNING_FRACTION:.0%} of them are"
    )
    return save_figure(figure, path)


def _variant_order(variant: str) -> tuple:
    """Variants by their value ('friction=0.25' before 'friction=1'); names without a number after them."""
    try:
        return (0, float(variant.split("=", 1)[1]), variant)
    except (IndexError, ValueError):
        return (1, 0.0, variant)


def pairwise_collisions_figure(runs: list[Run], path: Path) -> Path | None:
    """Fig. 7b: distribution of distinct touching body pairs per toss in the data, for each number of bodies."""
    counts = {}
    for run in runs:
        if run.summary["dataset"] == "multicubes" and "pairwise_collisions_true" in run.per_trajectory:
            counts.setdefault(int(run.value), run.per_trajectory["pairwise_collisions_true"])
    if not counts:
        return None
    figure = new_figure(figsize=(5, 3.6))
    axis = figure.subplots()
    bodies = sorted(counts)
    axis.boxplot([counts[k] for k in bodies], positions=bodies)
    axis.set_xlabel("bodies K")
    axis.set_ylabel("pairs that touch per toss")
    axis.set_title("Fig. 7b: pairwise collisions (ground truth)")
    return save_figure(figure, path)


def importance_table(runs: list[Run], method: Callable[[Run], str] | None = None) -> dict[str, dict[str, str]]:
    """Table 3 recomputed: 'Yes' when a method's mean test position error (over seeds too) varies across a
    dimension's variants by more than IMPORTANCE_THRESHOLD of its smallest value and by more than the widest min-max
    range over seeds among those variants (none with one seed), 'No' otherwise, 'N/A' without at least two
    variants. A method is a model, or what `method` names a run by (a model at one budget)."""
    method = method or (lambda run: run.summary["model"])
    table: dict[str, dict[str, str]] = {}
    for dataset, parameter in DIMENSIONS.items():
        chosen = [run for run in runs if run.summary["dataset"] == dataset]
        by_model: dict[str, list[list[Run]]] = {}
        for cell in seed_cells(chosen, lambda run: (method(run), run.summary["variant"])):
            by_model.setdefault(method(cell[0]), []).append(cell)
        for model, cells in by_model.items():
            spreads = [Spread.of([run.summary["pos_err"] for run in cell]) for cell in cells]
            errors = np.array([spread.mean for spread in spreads])
            if len(errors) < 2 or not np.all(np.isfinite(errors)):
                verdict = "N/A"
            else:
                change = errors.max() - errors.min()
                widest = max(spread.width for spread in spreads)
                verdict = "Yes" if change > IMPORTANCE_THRESHOLD * errors.min() and change > widest else "No"
            table.setdefault(model, {})[parameter] = verdict
    return table


def sensitivity_figure(runs: list[Run], dataset: str, variant: str, axis_key: str, path: Path) -> Path | None:
    """Test error against one observation axis (the other held plain) per model, with the 25-75% band across test
    trajectories and, with several seeds, their min-max as error bars; None unless some model was run at two or more
    values of the axis."""
    label, _ = OBSERVATION_AXES[axis_key]
    other = next(key for key in OBSERVATION_AXES if key != axis_key)
    chosen = [
        run
        for run in runs
        if (run.summary["dataset"], run.summary["variant"]) == (dataset, variant)
        and run.summary.get(other, OBSERVATION_AXES[other][1]) == OBSERVATION_AXES[other][1]
    ]
    value = lambda run: run.summary.get(axis_key, OBSERVATION_AXES[axis_key][1])  # noqa: E731
    grouped: dict[str, list[list[Run]]] = {}
    for cell in seed_cells(chosen, lambda run: (run.summary["model"], value(run))):
        grouped.setdefault(cell[0].summary["model"], []).append(cell)
    grouped = {model: cells for model, cells in grouped.items() if len(cells) > 1}
    if not grouped:
        return None
    figure = new_figure(figsize=(8.4, 3.4))
    axes = figure.subplots(1, 2)
    for axis, (key, metric) in zip(axes, PANELS[:2]):
        for model, cells in grouped.items():
            _plot_cells(axis, [value(cell[0]) for cell in cells], cells, key, model)
        axis.grid(True, alpha=0.3)
        axis.set_xlabel(label)
        axis.set_ylabel(metric)
    axes[0].legend(fontsize=8)
    clean = any(
        run.summary.get("scored_against") == "clean recording"
        for cells in grouped.values()
        for cell in cells
        for run in cell
    )
    against = "the clean recording" if clean else "the recording"
    shown = named_variants.label(dataset, variant)
    figure.suptitle(f"{dataset} {shown}: error vs {label.split(' (')[0]} (test, scored against {against})")
    return save_figure(figure, path)


def in_paper_figures(summary: dict) -> bool:
    """Whether a run is drawn in the paper's numbered figures (1, 2, 3, 5, 7a-c) and counted in Table 3: not a
    variant outside the benchmark's (friction=0.3), which the report names beside them (tables.custom_variants)."""
    return named_variants.paper_variant(summary["dataset"], summary["variant"]) is not False


def named_by_budget(runs: list[Run]) -> list[Run]:
    """The runs, each model named with its budget ('sysid (smoke)') when they hold more than one budget: a figure then
    draws a smoke and a quick fit as two lines, not one of them in the other's place."""
    if len({run.summary.get("budget") for run in runs}) < 2:
        return runs
    named = []
    for run in runs:
        model = f"{run.summary['model']} ({run.summary.get('budget') or 'unknown'})"
        named.append(Run({**run.summary, "model": model}, run.per_trajectory, run.path))
    return named


def draw_all(
    root: Path, out_dir: Path, every_run: list[Run] | None = None
) -> tuple[list[Path], dict[str, dict[str, str]]]:
    """Every figure the test runs under root allow (or those of every_run: the report's, each score once) and
    Table 3 over them. The paper's numbered figures and Table 3 hold the benchmark's variants only; the error over
    time and the sensitivity figures draw every variant, a custom one marked "not a paper variant". Runs of several
    budgets are drawn as a line per model and budget."""
    every_run = load_test_runs(root) if every_run is None else every_run
    table = importance_table([r for r in every_run if observed_plainly(r.summary) and in_paper_figures(r.summary)])
    every_run = named_by_budget(every_run)
    plain = [run for run in every_run if observed_plainly(run.summary)]
    runs = [run for run in plain if in_paper_figures(run.summary)]
    drawn = [sweep_figure(runs, dataset, out_dir / f"{dataset}.png") for dataset in SWEEPS]
    drawn.append(
        per_frame_figure(
            runs,
            "multicubes",
            "interbody_penetration_m",
            "max inter-body penetration (mm)",
            "Fig. 7a: inter-body penetration",
            out_dir / "fig7a_interbody_penetration.png",
        )
    )
    drawn.append(pairwise_collisions_figure(runs, out_dir / "fig7b_pairwise_collisions.png"))
    for dataset in sorted({run.summary["dataset"] for run in plain}):
        drawn.append(error_over_time_figure(plain, dataset, out_dir / f"error_over_time_{dataset}.png"))
    drawn.append(
        per_frame_figure(
            runs,
            "frictioncubes",
            "min_vertex_height_m",
            "lowest vertex height (mm)",
            "Fig. 7c: lowest vertex height, mu = 0 and 1",
            out_dir / "fig7c_lowest_vertex.png",
            values=[0.0, 1.0],
        )
    )
    for dataset, variant in sorted({(run.summary["dataset"], run.summary["variant"]) for run in every_run}):
        for axis_key in OBSERVATION_AXES:
            name = f"sensitivity_{axis_key}_{dataset}_{variant}".replace("=", "").replace(".", "p")
            drawn.append(sensitivity_figure(every_run, dataset, variant, axis_key, out_dir / f"{name}.png"))
    return [path for path in drawn if path is not None], table


def learning_curve_figure(curves: dict[tuple[str, str], list[tuple[float, float, float]]], path: Path) -> Path:
    """Held-out position and rotation error against training wall time; curves[(model, dataset)] = [(s, pos, rot)]."""
    datasets = sorted({dataset for _, dataset in curves})
    figure = new_figure(figsize=(4.5 * len(datasets), 6))
    axes = figure.subplots(2, len(datasets), squeeze=False)
    for column, dataset in enumerate(datasets):
        for (model, curve_dataset), points in sorted(curves.items()):
            if curve_dataset != dataset or not points:
                continue
            seconds, position, rotation = np.array(points).T
            axes[0, column].plot(seconds, position, marker="o", label=model, color=model_colour(model))
            axes[1, column].plot(seconds, rotation, marker="o", label=model, color=model_colour(model))
        axes[0, column].set_title(dataset)
        axes[0, column].set_ylabel("val position error (widths)")
        axes[1, column].set_ylabel("val rotation error (rad)")
        axes[1, column].set_xlabel("training wall time (s)")
        for axis in axes[:, column]:
            axis.set_yscale("log")
            axis.grid(True, which="both", alpha=0.3)
            axis.legend()
    return save_figure(figure, path)
