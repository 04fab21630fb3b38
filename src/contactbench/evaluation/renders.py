"""Headless renders with matplotlib (Agg; no display, no GPU, no OpenGL): final poses per method, rollout GIFs.

Every model is rebuilt from its run folder (`.hydra/config.yaml` + fitted checkpoint, as evaluate.py does) and rolled
out again on a few test trajectories, so renders need only the run folders and the dataset.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.colors import to_rgb
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection
from omegaconf import OmegaConf

from contactbench import restore, variants
from contactbench.evaluation.figures import observed_plainly
from contactbench.evaluation.plotting import TRUTH_COLOUR, model_colour, new_figure, save_figure
from contactbench.ground import Ground
from contactbench.kinematics import world_vertices
from contactbench.meshes import Mesh
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings

log = logging.getLogger(__name__)


@dataclass
class Rollouts:
    label: str  # dataset/variant
    truth: np.ndarray  # [n, T, K, 7]
    lengths: np.ndarray  # [n]
    predicted: dict[str, np.ndarray]  # model -> [n, T, K, 7]
    meshes: list[Mesh]
    dt: float  # s per frame
    floor_z: float
    ground: Ground  # the floor and any terrain on it


def rerun(train_dirs: list[Path], trajectories: int = 3) -> Rollouts:
    """Roll every fitted model of one dataset variant out again on the first `trajectories` test tosses."""
    predicted, truth = {}, None
    for train_dir in train_dirs:
        cfg = OmegaConf.load(train_dir / ".hydra" / "config.yaml")
        observed = restore.observed(cfg, read_recordings(Path(cfg.dataset.path), ["test"]))
        dataset = observed.dataset
        chosen = range(min(trajectories, dataset.split("test").n_trajectories))
        test = dataset.split("test").select(chosen)
        model = restore.load_fitted(cfg, dataset, train_dir)
        predicted[cfg.model.name] = model.rollout(dataset.scene, make_context(test, dataset.dt, cfg.context_frames))
        truth_split = observed.truth.split("test").select(chosen)
        truth, lengths = truth_split.poses, truth_split.lengths
        label = f"{cfg.dataset.name} {variants.label(cfg.dataset.name, cfg.dataset.variant)}"
        meshes = [dataset.body_mesh(k) for k in range(dataset.n_bodies)]
        dt, floor_z, ground = dataset.dt, dataset.floor_z, Ground.of(dataset)
    return Rollouts(label, truth, lengths, predicted, meshes, dt, floor_z, ground)


LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])


def _draw(axis, poses: np.ndarray, meshes: list[Mesh], colour: str, alpha: float = 1.0) -> None:
    """Solid bodies, each face shaded by its angle to a fixed light (coplanar triangles alike: no diagonals)."""
    base = np.array(to_rgb(colour))
    for k, mesh in enumerate(meshes):
        if not np.isfinite(poses[k]).all():
            continue
        corners = world_vertices(poses[k], mesh.vertices)
        triangles = corners[mesh.faces]  # [F, 3, 3]
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        shade = 0.45 + 0.55 * np.clip(normals @ LIGHT, 0.0, 1.0)
        colours = np.concatenate([base[None] * shade[:, None], np.full((len(shade), 1), alpha)], axis=1)
        axis.add_collection3d(Poly3DCollection(list(triangles), facecolors=colours, edgecolor="none", linewidths=0))


def _outline(axis, poses: np.ndarray, meshes: list[Mesh]) -> None:
    """The ground truth's edges only, thin and grey, so a model's panel shows where the bodies should be without
    hiding the model's own."""
    for k, mesh in enumerate(meshes):
        if np.isfinite(poses[k]).all():
            corners = world_vertices(poses[k], mesh.vertices)
            segments = [corners[[a, b]] for a, b in _feature_edges(mesh)]
            axis.add_collection3d(Line3DCollection(segments, colors=TRUTH_COLOUR, linewidths=0.6))


def _feature_edges(mesh: Mesh) -> list[tuple[int, int]]:
    """The mesh's edges between faces that are not coplanar (a cube's 12, not its faces' diagonals)."""
    triangles = mesh.vertices[mesh.faces]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    beside: dict[tuple[int, int], list[int]] = {}
    for face, (a, b, c) in enumerate(mesh.faces):
        for edge in ((a, b), (b, c), (c, a)):
            beside.setdefault(tuple(sorted(map(int, edge))), []).append(face)
    return [edge for edge, faces in beside.items() if len(faces) != 2 or normals[faces[0]] @ normals[faces[1]] < 0.999]


def _frame_axes(axis, rollouts: Rollouts, n: int) -> None:
    """Limits around the toss, a floor grid every 5 cm and a 10 cm scale bar on the floor; no ticks."""
    centres = np.concatenate(
        [rollouts.truth[n, : rollouts.lengths[n], :, :3].reshape(-1, 3)]
        + [p[n, : rollouts.lengths[n], :, :3].reshape(-1, 3) for p in rollouts.predicted.values()]
    )
    centres = centres[np.isfinite(centres).all(axis=1)]
    middle = np.median(centres, axis=0)
    reach = max(0.25, float(np.percentile(np.abs(centres[:, :2] - middle[:2]), 95)) + 0.1)
    low, high = middle[:2] - reach, middle[:2] + reach
    floor = rollouts.floor_z
    for x in np.arange(np.ceil(low[0] / 0.05) * 0.05, high[0], 0.05):
        axis.plot([x, x], [low[1], high[1]], [floor, floor], color="0.85", linewidth=0.5)
    for y in np.arange(np.ceil(low[1] / 0.05) * 0.05, high[1], 0.05):
        axis.plot([low[0], high[0]], [y, y], [floor, floor], color="0.85", linewidth=0.5)
    if not rollouts.ground.flat:  # the terrain's top surface over the panel, light grey
        x, y = np.meshgrid(np.linspace(low[0], high[0], 40), np.linspace(low[1], high[1], 40))
        top = rollouts.ground.height(torch.from_numpy(np.stack([x, y], axis=-1))).numpy()
        top[top <= floor + 1e-9] = np.nan
        axis.plot_surface(x, y, top, color="0.8", alpha=0.6, linewidth=0, antialiased=False, shade=True)
    start = low + 0.03
    axis.plot([start[0], start[0] + 0.1], [start[1], start[1]], [floor, floor], color="k", linewidth=2)
    axis.text(start[0], start[1] + 0.02, floor, "10 cm", fontsize=7)
    axis.set_xlim(low[0], high[0])
    axis.set_ylim(low[1], high[1])
    axis.set_zlim(floor, floor + reach)
    axis.set_box_aspect((1, 1, 0.5))
    axis.set_xticks([])
    axis.set_yticks([])
    axis.set_zticks([])


def final_poses_figure(rollouts: Rollouts, path: Path) -> Path:
    """Figs. 4 and 6 of the paper as small multiples: a row per toss, its last frame in a panel of its own for the
    ground truth (grey) and for each method (in its colour, the truth's outline beside it, the mean distance of its
    bodies from the truth's in the panel's title)."""
    count, panels = len(rollouts.truth), 1 + len(rollouts.predicted)
    figure = new_figure(figsize=(2.6 * panels, 2.7 * count + 0.5))
    for n in range(count):
        last = int(rollouts.lengths[n]) - 1
        truth = rollouts.truth[n, last]
        axis = figure.add_subplot(count, panels, n * panels + 1, projection="3d")
        _draw(axis, truth, rollouts.meshes, TRUTH_COLOUR)
        _frame_axes(axis, rollouts, n)
        axis.set_title(f"toss {n}: ground truth", fontsize=9)
        for column, (model, poses) in enumerate(rollouts.predicted.items(), start=2):
            axis = figure.add_subplot(count, panels, n * panels + column, projection="3d")
            _outline(axis, truth, rollouts.meshes)
            _draw(axis, poses[n, last], rollouts.meshes, model_colour(model))
            _frame_axes(axis, rollouts, n)
            off = np.nanmean(np.linalg.norm(poses[n, last, :, :3] - truth[:, :3], axis=-1)) * 100
            axis.set_title(f"{model}: {off:.1f} cm off", fontsize=9, color=model_colour(model))
    figure.suptitle(f"Final poses, {rollouts.label} (test): grey outline = ground truth")
    return save_figure(figure, path)


def rollout_gif(rollouts: Rollouts, path: Path, toss: int = 0, every: int = 3) -> Path:
    """An animation of one toss: ground truth and every method side by side (three panels a row), time in seconds."""
    panels = {"ground truth": rollouts.truth, **rollouts.predicted}
    columns = min(3, len(panels))
    rows = -(-len(panels) // columns)
    figure = new_figure(figsize=(3.6 * columns, 3.4 * rows + 0.4))
    axes = [figure.add_subplot(rows, columns, i + 1, projection="3d") for i in range(len(panels))]
    frames = range(0, int(rollouts.lengths[toss]), every)

    def show(t: int):
        for axis, (name, poses) in zip(axes, panels.items()):
            axis.cla()
            _draw(axis, poses[toss, t], rollouts.meshes, TRUTH_COLOUR if name == "ground truth" else model_colour(name))
            _frame_axes(axis, rollouts, toss)
            axis.set_title(name, fontsize=10)
        figure.suptitle(f"{rollouts.label}, test toss {toss}: t = {t * rollouts.dt:.2f} s", fontsize=11)
        return []

    animation = FuncAnimation(figure, show, frames=frames, blit=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial.gif")
    animation.save(partial, writer=PillowWriter(fps=round(1 / (rollouts.dt * every))), dpi=100)
    partial.replace(path)
    return path


# Which variants the report renders (the paper's Figs. 4 and 6 show a single cube and several), when present.
RENDERED = (
    ("frictioncubes", "friction=0.5"),
    ("multicubes", "bodies=3"),
    ("polyhedra", "faces=12"),
    ("nonconvex", "shape=ring"),
    ("terrain", "ground=ramp,faces=6"),
    ("articulated", "joint_damping=0.005"),
    ("contactnets_cube", None),
    ("contactnets_elbow", None),
)


def render_report(root: Path, out_dir: Path) -> list[Path]:
    """Final-pose figures for the RENDERED variants found under root (else the first variant) and one GIF."""
    groups: dict[tuple[str, str], list[Path]] = {}
    for metrics in sorted(Path(root).rglob("test/metrics.json")):
        run_dir = metrics.parent.parent
        summary = json.loads(metrics.read_text())
        if (run_dir / ".hydra" / "config.yaml").is_file() and observed_plainly(summary):
            groups.setdefault((summary["dataset"], summary["variant"]), []).append(run_dir)
    chosen = [key for key in groups if any(key[0] == d and (v is None or key[1] == v) for d, v in RENDERED)] or list(
        groups
    )[:1]
    drawn = []
    for dataset, variant in chosen:
        try:
            rollouts = rerun(groups[(dataset, variant)])
        except Exception as error:  # noqa: BLE001 - a render is an extra: say why it is missing, keep the report
            log.warning("no render for %s %s: %s", dataset, variant, error)
            continue
        stem = f"{dataset}_{variant or 'recorded'}".replace("=", "").replace(".", "p")
        drawn.append(final_poses_figure(rollouts, Path(out_dir) / f"final_poses_{stem}.png"))
        if len(drawn) == 1:
            drawn.append(rollout_gif(rollouts, Path(out_dir) / f"rollout_{stem}.gif"))
    return drawn
