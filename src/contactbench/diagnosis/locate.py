"""Step 1, locate: where the base simulator's short-horizon residual lies, by contact phase, component and body."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from contactbench.diagnosis.library import Hypothesis
from contactbench.diagnosis.phases import FREE, PHASES, label_phases
from contactbench.diagnosis.segments import COMPONENTS, residual_parts

if TYPE_CHECKING:
    from contactbench.diagnosis.state import Diagnosis


def locate(steps: Diagnosis, hypothesis: Hypothesis, values: np.ndarray) -> dict:
    """Squared residual on val by phase x component (and body), with bootstrap intervals over trajectories."""
    segments = steps.val_fit.simulator.segments
    poses, unstable = steps.val_fit.simulator.predict([hypothesis.contact_parameters(values)])
    parts = residual_parts(segments, poses[0])
    # [M, K, component]: squared residual summed over the segment's frames
    squared = np.stack([np.nansum(parts[c] ** 2, axis=1) for c in COMPONENTS], axis=-1)
    squared[unstable[0]] = np.nan
    squared = np.nan_to_num(squared)
    n_traj = steps.val_split.n_trajectories
    table = np.zeros((n_traj, len(PHASES), len(COMPONENTS)))  # per trajectory, phase, component
    for k in range(steps.dataset.n_bodies):
        np.add.at(table, (segments.trajectory, segments.phase[:, k]), squared[:, k])
    # The angular residual in each body's own frame: which body axis the rotation error turns about.
    body_axes = np.nansum(np.nan_to_num(parts["body_angular"]) ** 2, axis=(0, 1, 2))
    body_totals = np.zeros((n_traj, steps.dataset.n_bodies))
    np.add.at(body_totals, segments.trajectory, squared.sum(axis=-1))
    frames = np.zeros((n_traj, len(PHASES)))
    for k in range(steps.dataset.n_bodies):
        np.add.at(frames, (segments.trajectory, segments.phase[:, k]), 1)
    total = table.sum()
    picks = steps.rng.integers(0, n_traj, size=(steps.budget.bootstrap, n_traj))
    resampled = table[picks].sum(axis=1)  # [draws, phase, component]
    shares = resampled / resampled.sum(axis=(1, 2), keepdims=True)
    phase_share = table.sum(axis=(0, 2)) / total
    phase_ci = np.percentile(shares.sum(axis=2), [2.5, 97.5], axis=0)
    cell = table.sum(axis=0) / total
    cell_ci = np.percentile(shares, [2.5, 97.5], axis=0)
    segment_share = frames.sum(axis=0) / frames.sum()
    noise = noise_floor(steps)
    per_segment = table.sum(axis=0).sum(axis=1) / np.maximum(frames.sum(axis=0), 1)  # mean squared residual per segment
    worst_phase, worst_component = np.unravel_index(np.argmax(cell), cell.shape)
    return {
        "phase_shares": {p: float(phase_share[i]) for i, p in enumerate(PHASES)},
        "phase_shares_ci95": {p: [float(phase_ci[0, i]), float(phase_ci[1, i])] for i, p in enumerate(PHASES)},
        "segment_shares": {p: float(segment_share[i]) for i, p in enumerate(PHASES)},
        "cells": {f"{p}/{c}": float(cell[i, j]) for i, p in enumerate(PHASES) for j, c in enumerate(COMPONENTS)},
        "cells_ci95": {
            f"{p}/{c}": [float(cell_ci[0, i, j]), float(cell_ci[1, i, j])]
            for i, p in enumerate(PHASES)
            for j, c in enumerate(COMPONENTS)
        },
        "body_shares": (body_totals.sum(axis=0) / body_totals.sum()).tolist(),
        "angular_body_frame_shares": dict(zip("xyz", (body_axes / max(body_axes.sum(), 1e-300)).tolist())),
        "mean_squared_residual_per_segment": {p: float(per_segment[i]) for i, p in enumerate(PHASES)},
        "noise_floor_per_segment": noise,
        "above_noise_floor": {p: bool(per_segment[i] > 3 * noise) for i, p in enumerate(PHASES)},
        "where": f"{PHASES[worst_phase]}/{COMPONENTS[worst_component]}",
        "total_squared_residual": float(total),
    }


def noise_floor(steps: Diagnosis) -> float:
    """Squared residual per segment that measurement noise alone would leave (a perfect simulator's).

    Position noise sigma comes from free-flight frames, where the second difference of positions must equal
    g dt^2 exactly; a segment restarted from a noisy pose and a finite-difference velocity then drifts by
    about sigma sqrt(2 + 2 j^2) after j frames (in half-widths, as the residuals)."""
    split, dt = steps.val_split, steps.dataset.dt
    labels = label_phases(steps.dataset, split)
    poses = split.poses[..., :3]
    second = poses[:, 2:] - 2 * poses[:, 1:-1] + poses[:, :-2] - steps.dataset.gravity * dt**2  # [N, T-2, K, 3]
    free = (labels[:, 1:-1] == FREE) & (labels[:, 2:] == FREE) & (labels[:, :-2] == FREE)
    if not free.any():
        return 0.0
    sigma = float(np.sqrt(np.mean(second[free] ** 2) / 6.0))  # var(x_{t+1} - 2 x_t + x_{t-1}) = 6 sigma^2 per axis
    half_width = float(steps.dataset.widths().mean()) / 2
    frames = np.arange(1, steps.budget.segment_frames + 1)
    return float(3 * np.sum(2 + 2 * frames**2) * (sigma / half_width) ** 2 * steps.dataset.n_bodies)
