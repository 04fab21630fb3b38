"""The contact signatures' statistics: least-squares fits of rows (diagnosis.contact_rows) for every resample of the
tosses (the frames of a toss count together), each a point estimate with a percentile interval."""

from __future__ import annotations

import numpy as np

from contactbench.diagnosis.contact_rows import Rows
from contactbench.diagnosis.free_flight import least_squares_by_toss

# Floor cells for the friction's (and the bounce's) dependence on position, in body widths; a cell counts with at
# least MIN_CELL_TOSSES tosses and MIN_CELL_FRAMES frames in it (fewer left a dodecahedron's cell fit singular).
FRICTION_CELL = 2.0
BOUNCE_CELL = 4.0
MIN_CELL_TOSSES = 5
MIN_CELL_FRAMES = 10
# Fewer tosses than this with frames of a signature in a split: no interval is given (INCONCLUSIVE).
MIN_TOSSES = 20


def fit(rows: Rows, design: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Least squares of rows.response on `design` [F, P] for every resample: [draws + 1, P]."""
    return least_squares_by_toss(rows.toss, design, rows.response, weights)


def _interval(samples: np.ndarray, confidence: float) -> list[float]:
    tail = (1.0 - confidence) / 2 * 100
    return [float(v) for v in np.percentile(samples, [tail, 100 - tail])]


def _summary(draws: np.ndarray, confidence: float, rows: Rows, **extra) -> dict:
    return {
        "n_tosses": int(len(np.unique(rows.toss))),
        "n_frames": int(len(rows.toss)),
        "value": float(draws[0]),
        "ci": _interval(draws[1:], confidence),
        **extra,
    }


def _debiased(squares: np.ndarray, noise: float) -> np.ndarray:
    """A size from squared sizes per draw, less the resampling noise that inflates them: the point estimate loses it
    once, the draws (noisy around a noisy point) twice; signed square root."""
    corrected = np.concatenate([squares[:1] - noise, squares[1:] - 2 * noise])
    return np.sign(corrected) * np.sqrt(np.abs(corrected))


def _harmonics(angle: np.ndarray) -> np.ndarray:
    """mu(theta) / mu0 - 1 terms: cos 2 theta, sin 2 theta (anisotropy: friction depends on the axis of the slip),
    cos theta, sin theta (a steady push along one direction, e.g. a tilted floor, which friction cannot be)."""
    return np.stack([np.cos(2 * angle), np.sin(2 * angle), np.cos(angle), np.sin(angle)], axis=-1)


def _with_direction(rows: Rows, design: np.ndarray) -> np.ndarray:
    """The design with the slip direction's harmonics beside it (sliding rows), so that an anisotropy does not pass
    for a dependence on speed or position where directions and speeds or places go together."""
    if "angle" not in rows.extra:
        return design
    return np.concatenate([design, rows.design * _harmonics(rows.extra["angle"])], axis=1)


def anisotropy(rows: Rows, weights: np.ndarray, confidence: float) -> dict:
    """mu(theta) = mu0 (1 + a cos 2 theta + b sin 2 theta + first-harmonic nuisance), theta the slip direction in
    the world frame: the amplitude sqrt(a^2 + b^2) (debiased) and the axis of largest friction."""
    design = _with_direction(rows, rows.design)
    coefficients = fit(rows, design, weights)
    relative = coefficients[:, 1:] / coefficients[:, :1]
    squares = relative[:, 0] ** 2 + relative[:, 1] ** 2
    amplitude = _debiased(squares, float(relative[1:, 0].var() + relative[1:, 1].var()))
    a, b = relative[0, 0], relative[0, 1]
    return _summary(
        amplitude,
        confidence,
        rows,
        mu0=float(coefficients[0, 0]),
        mu0_ci=_interval(coefficients[1:, 0], confidence),
        axis_deg=float(np.degrees(np.arctan2(b, a) / 2)),
        ratio=float((1 + np.hypot(a, b)) / max(1 - np.hypot(a, b), 1e-9)),
        push_of_mu=float(np.hypot(relative[0, 2], relative[0, 3])),
    )


def speed_change(rows: Rows, weights: np.ndarray, confidence: float, relative: bool) -> dict:
    """A quantity linear in the speed, q = q0 + q1 (s - s_median): its change q1 (s90 - s10) over the central 80% of
    the speeds, relative to q0 where `relative`."""
    speed = rows.extra["speed"]
    low, middle, high = np.percentile(speed, [10, 50, 90])
    design = _with_direction(rows, rows.design * np.stack([np.ones_like(speed), speed - middle], axis=-1))
    coefficients = fit(rows, design, weights)
    change = coefficients[:, 1] * (high - low) / (coefficients[:, 0] if relative else 1.0)
    return _summary(change, confidence, rows, speeds_m_s=[float(low), float(high)], at_median=float(coefficients[0, 0]))


def cell_spread(rows: Rows, weights: np.ndarray, confidence: float, cell: float, relative: bool) -> dict:
    """One value per floor cell (square, `cell` metres) that MIN_CELL_TOSSES tosses visit: their frame-weighted spread
    (relative to their mean where `relative`), debiased by each cell value's resampling noise. A resample that
    misses every toss of a cell leaves that cell out."""
    cells = np.floor(rows.extra["position"] / cell).astype(int)
    labels, index = np.unique(cells, axis=0, return_inverse=True)
    index = index.reshape(-1)
    tosses_per_cell = np.array([len(np.unique(rows.toss[index == c])) for c in range(len(labels))])
    visited = (tosses_per_cell >= MIN_CELL_TOSSES) & (np.bincount(index, minlength=len(labels)) >= MIN_CELL_FRAMES)
    inside = visited[index]
    tosses = len(np.unique(rows.toss[inside]))
    if visited.sum() < 2 or tosses < MIN_TOSSES:
        return {"n_tosses": tosses, "n_frames": int(inside.sum()), "cells": int(visited.sum())}
    kept = Rows(
        rows.toss[inside],
        rows.design[inside],
        rows.response[inside],
        {key: value[inside] for key, value in rows.extra.items()},
    )
    column = (np.cumsum(visited) - 1)[index[inside]]
    n_cells = int(visited.sum())
    design = np.zeros((len(column), n_cells))
    design[np.arange(len(column)), column] = kept.design[:, 0]
    values = fit(kept, _with_direction(kept, design), weights)[:, :n_cells]  # [draws + 1, cells]
    per_toss = np.zeros((weights.shape[1], n_cells))
    np.add.at(per_toss, (kept.toss, column), 1)
    frames = weights @ per_toss  # [draws + 1, cells] each cell's frames in each resample
    share = frames / frames.sum(axis=1, keepdims=True)
    mean = np.sum(values * share, axis=1)
    squares = np.sum((values - mean[:, None]) ** 2 * share, axis=1)
    present = frames[1:] > 0
    deviation = np.where(present, values[1:] - values[0], 0.0)
    noise = float(np.sum(deviation**2, axis=0) / np.maximum(present.sum(axis=0), 1) @ share[0])
    scale = mean**2 if relative else np.ones_like(mean)
    return _summary(
        _debiased(squares / scale, noise / float(scale[0])),
        confidence,
        kept,
        cells=int(visited.sum()),
        cell_m=cell,
        lowest_highest=[float(values[0].min()), float(values[0].max())],
    )


def held_share(held: np.ndarray, weights: np.ndarray, confidence: float) -> dict:
    """The share of flat sliding frames whose spin is held below HELD_SPIN (counts only from too few tosses)."""
    counts = {"n_tosses": int((held[:, 1] > 0).sum()), "n_frames": int(held[:, 1].sum())}
    if counts["n_tosses"] < MIN_TOSSES:
        return counts
    sums = weights @ held
    share = sums[:, 0] / np.maximum(sums[:, 1], 1)
    return {**counts, "value": float(share[0]), "ci": _interval(share[1:], confidence)}


def coefficient(rows: Rows, weights: np.ndarray, confidence: float) -> dict:
    """The first coefficient of the rows' own design."""
    return _summary(fit(rows, rows.design, weights)[:, 0], confidence, rows)


def rolling_resistance(rows: Rows, weights: np.ndarray, confidence: float) -> dict:
    """Rolling resistance per load, and the same beside a resistance that grows with the roll's speed (what a force at
    the centre, a viscous floor or drag, or a spin damping adds about the contact)."""
    beside_viscous = fit(rows, rows.design, weights)
    return _summary(
        fit(rows, rows.design[:, :1], weights)[:, 0],
        confidence,
        rows,
        beside_viscous=float(beside_viscous[0, 0]),
        beside_viscous_ci=_interval(beside_viscous[1:, 0], confidence),
    )
