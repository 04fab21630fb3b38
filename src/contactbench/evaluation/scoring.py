"""Score a contact model on one split with the shared protocol and write metrics.json and its CSVs."""

from __future__ import annotations

import csv
import io
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contactbench import atomic, variants
from contactbench.ground import Ground
from contactbench.metrics import MetricsResult, compute_metrics
from contactbench.models.base import ContactModel
from contactbench.protocol import make_context
from contactbench.scene import Recordings, Split

log = logging.getLogger(__name__)


@dataclass
class Score:
    header: dict  # model, dataset, variant, split, n_trajectories, context_frames
    metrics: MetricsResult
    rollout_seconds: float

    def summary(self) -> dict:
        return {**self.header, **self.metrics.summary, "rollout_seconds": round(self.rollout_seconds, 3)}


def score_model(
    model: ContactModel,
    dataset: Recordings,
    split: str,
    context_frames: int,
    *,
    dataset_name: str,
    variant: str,
    truth: Split | None = None,
    annotations: dict | None = None,
) -> Score:
    """Roll the model out from the first `context_frames` frames of every trajectory in `split` and score the rest
    against `truth` (the same trajectories, e.g. without the observation's noise; by default the split itself).
    `annotations` join the header (how the data were observed, the variant's values)."""
    recorded = dataset.split(split)
    reference = recorded if truth is None else truth
    if reference.poses.shape[:3] != recorded.poses.shape[:3]:
        raise ValueError(f"truth has poses of shape {reference.poses.shape}, the split {recorded.poses.shape}")
    context = make_context(recorded, dataset.dt, context_frames)
    started = time.perf_counter()
    predicted = model.rollout(dataset.scene, context)
    elapsed = time.perf_counter() - started
    expected = (recorded.n_trajectories, context.horizon, dataset.n_bodies, 7)
    if predicted.shape != expected:
        raise ValueError(f"model {model.name!r} returned poses of shape {predicted.shape}, expected {expected}")
    metrics = compute_metrics(
        reference.poses[:, : context.horizon],
        predicted,
        recorded.lengths,
        context_frames,
        [dataset.body_mesh(k) for k in range(dataset.n_bodies)],
        dataset.floor_z,
        ground=None if dataset.flat else Ground.of(dataset),
        joints=dataset.joints,
    )
    header = {
        "model": model.name,
        "dataset": dataset_name,
        "variant": variant,
        "split": split,
        "n_trajectories": recorded.n_trajectories,
        "context_frames": context_frames,
        **(annotations or {}),
    }
    return Score(header, metrics, elapsed)


def _json_number(value):
    if isinstance(value, (np.floating, float)):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


def _csv_text(columns: dict[str, np.ndarray]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    names = list(columns)
    writer.writerow(names)
    for row in zip(*(np.asarray(columns[name]).tolist() for name in names)):
        writer.writerow(row)
    return buffer.getvalue()


def write_score(score: Score, out_dir: Path) -> dict:
    """metrics.json (summary + per-frame curves), per_frame.csv and per_trajectory.csv in out_dir."""
    out_dir = Path(out_dir)
    per_frame = {"frame": np.arange(len(next(iter(score.metrics.per_frame.values())))), **score.metrics.per_frame}
    document = {key: _json_number(value) for key, value in score.summary().items()}
    document["per_frame"] = {
        key: [_json_number(x) for x in np.asarray(values).tolist()] for key, values in per_frame.items()
    }
    atomic.write_json(out_dir / "metrics.json", document)
    atomic.write_text(out_dir / "per_frame.csv", _csv_text(per_frame))
    atomic.write_text(
        out_dir / "per_trajectory.csv",
        _csv_text({"trajectory": np.arange(score.header["n_trajectories"]), **score.metrics.per_trajectory}),
    )
    log.info(
        "%s on %s/%s %s (%d trajectories): pos_err %.4f  rot_err %.4f rad  floor penetration %.2e m (recorded %.2e m)",
        score.header["model"],
        score.header["dataset"],
        variants.label(score.header["dataset"], score.header["variant"]),
        score.header["split"],
        score.header["n_trajectories"],
        score.metrics.summary["pos_err"],
        score.metrics.summary["rot_err_rad"],
        score.metrics.summary["floor_penetration_m"],
        score.metrics.summary["floor_penetration_true_m"],
    )
    return document
