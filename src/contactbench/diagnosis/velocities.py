"""Whether recorded velocities follow the simulators' convention, and the recordings aligned to it where they do not.

The diagnosis restarts MuJoCo from recorded states. MuJoCo and Bullet integrate semi-implicitly, one step per frame:
x_t = x_{t-1} + dt v_t, so the velocity they store after a step is the backward difference of positions. Recordings
may store another velocity: an engine stepping several times per frame, or a tracker's instantaneous estimate, gives
in free flight v_t = (x_t - x_{t-1}) / dt + c g dt (c = 1/2 for the exact parabola, 3/7 for seven substeps). A
simulator restarted from such a state falls short by c g dt^2 every frame: a steady, predictable residual in free
flight that is no physics (two null datasets of an independent generator with seven substeps per frame came out
`unexplained` in free flight because of it). It is measured model-free where nothing else acts, in free flight: the
recorded linear velocity of the mesh frame's origin minus the backward difference of its position, a constant per
axis, with an interval from resampling tosses. Where train and val both show it (interval clear of zero and beyond
MARGIN), the recorded linear velocities are shifted by train's offset before any step uses them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from contactbench.diagnosis.free_flight import SPLITS, free_frames, resample_weights
from contactbench.scene import Recordings, Split

# The offset must exceed this fraction of |g| dt (the velocity gravity adds in one frame) to count: 1/2 and 3/7 of it
# are the conventions above; PyBullet data stored by the project's generator show 0 to rounding.
MARGIN = 0.05


def measure(dataset: Recordings, split: Split, rng: np.random.Generator, draws: int, confidence: float) -> dict:
    """Recorded minus backward-difference linear velocity over the split's free-flight frames (m/s per axis)."""
    free = free_frames(dataset, split)
    free[:, 0] = False  # frame 0 has no backward difference
    used, rows = np.unique(np.nonzero(free)[0], return_inverse=True)
    if split.velocities is None or len(used) < 2:
        return {"n_trajectories": int(len(used))}
    backward = np.zeros_like(split.poses[..., :3])
    backward[:, 1:] = np.diff(split.poses[..., :3], axis=1) / dataset.dt
    offsets = (split.velocities[..., :3] - backward)[free]  # [F, 3]
    sums, counts = np.zeros((len(used), 3)), np.bincount(rows, minlength=len(used)).astype(float)
    np.add.at(sums, rows, offsets)
    weights = resample_weights(len(used), rng, draws)[1:]
    samples = (weights @ sums) / (weights @ counts)[:, None]  # [draws, 3]
    tail = (1.0 - confidence) / 2 * 100
    return {
        "n_trajectories": int(len(used)),
        "offset": (sums.sum(axis=0) / counts.sum()).tolist(),
        "ci95": np.percentile(samples, [tail, 100 - tail], axis=0).T.tolist(),  # [axis] -> [low, high]
    }


def check(dataset: Recordings, rng: np.random.Generator, draws: int = 1000, confidence: float = 0.95) -> dict:
    """The offset per split, and whether the recordings are to be aligned (train and val show it, on the same side)."""
    splits = {
        name: measure(dataset, dataset.split(name), rng, draws, confidence) for name in SPLITS if name in dataset.splits
    }
    frame = float(np.linalg.norm(dataset.gravity)) * dataset.dt
    train, val = splits.get("train", {}), splits.get("val", {})
    shown = [
        "ci95" in train
        and "ci95" in val
        and all(np.sign(part["ci95"][axis][0]) == np.sign(part["ci95"][axis][1]) for part in (train, val))
        and np.sign(train["offset"][axis]) == np.sign(val["offset"][axis])
        and min(abs(part["offset"][axis]) for part in (train, val)) > MARGIN * frame
        for axis in range(3)
    ]
    offset = [train["offset"][axis] if shown[axis] else 0.0 for axis in range(3)]
    out = {"splits": splits, "margin_m_s": MARGIN * frame, "aligned": any(shown), "offset": offset}
    out["sentence"] = sentence(out, frame)
    return out


def sentence(found: dict, frame: float) -> str:
    if found["aligned"]:
        offset = np.asarray(found["offset"])
        return (
            f"Recorded velocities differ from the backward differences of the positions by {_vector(offset)} m/s in "
            f"free flight ({np.linalg.norm(offset) / frame:.2f} of g dt): not the one-step semi-implicit convention "
            "the simulators restart from, so every step uses the recorded velocities minus that offset."
        )
    if all("ci95" in part for part in found["splits"].values()) and found["splits"]:
        return "Recorded velocities are the backward differences of the positions in free flight, as the simulators'."
    return "No recorded velocities, or too few free-flight frames to compare them: velocities as recorded or estimated."


def aligned(dataset: Recordings, found: dict) -> Recordings:
    """The recordings with train's offset taken off every split's recorded linear velocities (unchanged if none)."""
    if not found["aligned"]:
        return dataset
    shift = np.zeros(6)
    shift[:3] = found["offset"]
    splits = {
        name: split if split.velocities is None else dataclasses.replace(split, velocities=split.velocities - shift)
        for name, split in dataset.splits.items()
    }
    return dataclasses.replace(dataset, splits=splits)


def _vector(values: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:+.4f}" for v in values) + ")"
