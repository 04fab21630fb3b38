"""A model-free first check: do bodies in free flight fall at meta.gravity?

In free flight the centre of mass obeys x'' = g exactly, so the second difference of its recorded positions over
dt^2 measures the acceleration the recordings actually show, with no simulator and no fitted parameter. A
vertical acceleration other than meta.gravity means the recordings' time base or length scale is off (a true frame
interval of sqrt(a / g) dt, or positions scaled by a / g), or meta.gravity itself is wrong; MuJoCo can express all
three as a scaled gravity (library effect `gravity_scale`). Fit on train, decide on val, confirm on test. Only an
acceleration that is the same for every frame is an apparent gravity: one that grows with speed (air drag, wind) or
points across gravity is a force, and the diagnosis must find it elsewhere.
"""

from __future__ import annotations

import numpy as np

from contactbench import rotations
from contactbench.kinematics import world_vertices
from contactbench.recordings import Recordings, Split

SPLITS = ("train", "val", "test")
# A frame counts as free flight when, at it and at both neighbours, the body's lowest vertex is this fraction of its
# width above the floor (2 cm for the 10.5 cm real cube; contact and the tracker's filtering stay out of it) and no
# other body's bounding sphere comes within that distance of its own.
CLEARANCE = 0.2
# The deviation must be at least this fraction of |meta.gravity| to count (the decision rule's practical margin).
MARGIN = 0.005


def free_frames(dataset: Recordings, split: Split) -> np.ndarray:
    """[N, T, K] True where body k is in free flight (see CLEARANCE) at frames t-1, t and t+1 (False at the ends)."""
    poses = np.nan_to_num(split.poses)
    widths = dataset.widths()
    clear = np.zeros(poses.shape[:3], dtype=bool)
    radii = []
    for k in range(dataset.n_bodies):
        vertices = dataset.body_mesh(k).vertices
        radii.append(float(np.linalg.norm(vertices, axis=1).max()))
        lowest = world_vertices(poses[:, :, k], vertices)[..., 2].min(axis=-1) - dataset.floor_z
        clear[:, :, k] = lowest > CLEARANCE * widths[k]
    for k in range(dataset.n_bodies):
        for j in range(dataset.n_bodies):
            if j != k:
                gap = np.linalg.norm(poses[:, :, k, :3] - poses[:, :, j, :3], axis=-1) - radii[k] - radii[j]
                clear[:, :, k] &= gap > CLEARANCE * widths[k]
    clear &= split.valid_mask()[..., None]
    clear &= np.isfinite(split.poses).all(axis=-1)
    free = np.zeros_like(clear)
    free[:, 1:-1] = clear[:, :-2] & clear[:, 1:-1] & clear[:, 2:]
    return free


def centre_motion(dataset: Recordings, split: Split) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference velocities and accelerations of the centres of mass [N, T, K, 3] (zero at the ends)."""
    poses = np.nan_to_num(split.poses)
    centres = np.stack(
        [
            poses[:, :, k, :3] + rotations.rotate(poses[:, :, k, 3:], dataset.mass_properties(k)[0])
            for k in range(dataset.n_bodies)
        ],
        axis=2,
    )  # [N, T, K, 3]
    velocity, acceleration = np.zeros_like(centres), np.zeros_like(centres)
    velocity[:, 1:-1] = (centres[:, 2:] - centres[:, :-2]) / (2 * dataset.dt)
    acceleration[:, 1:-1] = (centres[:, 2:] - 2 * centres[:, 1:-1] + centres[:, :-2]) / dataset.dt**2
    return velocity, acceleration


def centre_accelerations(dataset: Recordings, split: Split) -> tuple[np.ndarray, np.ndarray]:
    """Per trajectory: the summed free-flight accelerations of the centres of mass [N, 3] (m/s^2) and their count
    [N]."""
    free = free_frames(dataset, split)
    sums = np.einsum("ntk,ntki->ni", free.astype(float), centre_motion(dataset, split)[1])
    return sums, free.sum(axis=(1, 2))


def gravity_like(dataset: Recordings, split: Split) -> dict:
    """Whether the free-flight acceleration is a gravity (the same for every frame) rather than a force that depends
    on the motion: the part along gravity that grows as drag does, k |v| (v . down) fitted by least squares, at the
    median such value, and the mean part across gravity, each against MARGIN of |meta.gravity|. A wrong time base or
    length scale scales the whole acceleration; air drag, wind, or frames resting on a tilted floor do not."""
    free = free_frames(dataset, split)
    velocity, acceleration = (part[free] for part in centre_motion(dataset, split))  # [F, 3]
    gravity = np.asarray(dataset.gravity, dtype=float)
    g = float(np.linalg.norm(gravity))
    down = gravity / g
    along = acceleration @ down
    drag_like = -np.linalg.norm(velocity, axis=-1) * (velocity @ down)
    design = np.stack([np.ones_like(drag_like), drag_like], axis=1)
    (_, slope), *_ = np.linalg.lstsq(design, along, rcond=None)
    speed_term = float(abs(slope) * np.median(np.abs(drag_like)))
    across = float(np.linalg.norm(acceleration.mean(axis=0) - (acceleration.mean(axis=0) @ down) * down))
    return {
        "speed_dependent_m_s2": speed_term,
        "across_gravity_m_s2": across,
        "gravity_like": bool(speed_term < MARGIN * g and across < MARGIN * g),
    }


def measure(dataset: Recordings, split: Split, rng: np.random.Generator, draws: int, confidence: float = 0.95) -> dict:
    """Mean free-flight acceleration of one split, its standard error and a percentile interval (resampling
    trajectories, so that frames of one toss count together)."""
    sums, counts = centre_accelerations(dataset, split)
    used = counts > 0
    sums, counts = sums[used], counts[used]
    if not len(counts):
        return {"n_trajectories": 0, "n_frames": 0}
    mean = sums.sum(axis=0) / counts.sum()
    picks = rng.integers(0, len(counts), size=(draws, len(counts)))
    samples = sums[picks].sum(axis=1) / np.maximum(counts[picks].sum(axis=1), 1)[:, None]  # [draws, 3]
    tail = (1.0 - confidence) / 2 * 100
    return {
        "n_trajectories": int(len(counts)),
        "n_frames": int(counts.sum()),
        "acceleration": mean.tolist(),
        "sem": samples.std(axis=0).tolist(),
        "ci95": np.percentile(samples, [tail, 100 - tail], axis=0).T.tolist(),  # [axis] -> [low, high]
    }


def check(dataset: Recordings, rng: np.random.Generator, draws: int = 1000, confidence: float = 0.95) -> dict:
    """The free-flight finding: accelerations per split; the scale a/g along meta.gravity fitted on train; whether
    val says it differs from 1 (interval excludes it, by at least MARGIN); whether test confirms the same side."""
    gravity = np.asarray(dataset.gravity, dtype=float)
    g = float(np.linalg.norm(gravity))
    down = gravity / g
    splits = {
        name: measure(dataset, dataset.split(name), rng, draws, confidence) for name in SPLITS if name in dataset.splits
    }
    out: dict = {"meta_gravity": gravity.tolist(), "clearance_of_width": CLEARANCE, "margin": MARGIN, "splits": splits}
    for part in splits.values():
        if part["n_frames"]:
            part["along_gravity"] = float(np.dot(part["acceleration"], down))
            # along meta.gravity: the interval of the projection (gravity lies along an axis in practice)
            axis = int(np.argmax(np.abs(down)))
            part["along_gravity_ci95"] = sorted(float(np.sign(down[axis]) * c) for c in part["ci95"][axis])
            part["along_gravity_sem"] = float(part["sem"][axis])
            part["scale"] = part["along_gravity"] / g
    train, val, test = (splits.get(name, {}) for name in SPLITS)
    if not all(part.get("n_frames") for part in (train, val, test)):
        out.update(
            scale=None,
            differs=False,
            confirmed=False,
            sentence="Too few free-flight frames in some split to measure the free-fall acceleration.",
        )
        return out
    scale = train["scale"]
    low, high = (c / g for c in val["along_gravity_ci95"])
    differs = bool((low > 1 or high < 1) and abs(val["scale"] - 1) >= MARGIN)
    test_low, test_high = (c / g for c in test["along_gravity_ci95"])
    confirmed = bool(differs and ((test_low > 1) if low > 1 else (test_high < 1)))
    shape = gravity_like(dataset, dataset.split("val"))
    out.update(
        **shape,
        # what the gravity_scale effect may lean on: a differing acceleration that is a gravity, not a drag
        apparent_gravity=bool(differs and shape["gravity_like"]),
        scale=scale,
        frame_interval_factor=float(np.sqrt(scale)),  # the true frame interval / meta.dt, if the time base is off
        frame_rate=float(1.0 / (np.sqrt(scale) * dataset.dt)),
        length_scale=scale,  # recorded / true lengths, if the length scale is off
        differs=differs,
        confirmed=confirmed,
    )
    out["sentence"] = sentence(out)
    return out


def sentence(found: dict) -> str:
    """One line for the report: X +- SEM vs meta per split, and what it means."""
    g = float(np.linalg.norm(found["meta_gravity"]))
    parts = ", ".join(
        f"{name} {part['along_gravity']:.3f} ± {part['along_gravity_sem']:.3f}"
        for name, part in found["splits"].items()
    )
    head = f"Free-flight acceleration along gravity (m/s², mean ± SE): {parts}; meta.gravity {g:.3f}"
    if not found["differs"]:
        return head + ": consistent with meta (val)."
    verdict = "confirmed on test" if found["confirmed"] else "NOT confirmed on test"
    if not found["gravity_like"]:
        return (
            f"{head}: {found['scale']:.4f} × meta (train), differs on val, {verdict}; but not a gravity: on val it "
            f"varies with the motion ({found['speed_dependent_m_s2']:.3f} m/s² as drag would grow) or points across "
            f"gravity ({found['across_gravity_m_s2']:.3f} m/s²), so a force acts in free flight (drag, wind) or "
            f"bodies counted as flying rest on something."
        )
    return (
        f"{head}: apparent gravity {found['scale']:.4f} × meta (train), differs on val, {verdict}, the same for every "
        f"frame (as drag would grow: {found['speed_dependent_m_s2']:.3f} m/s²). Either the true frame interval is "
        f"{found['frame_interval_factor']:.4f} × meta.dt ({found['frame_rate']:.1f} Hz), or lengths are recorded at "
        f"{found['length_scale']:.4f} × true, or meta.gravity is wrong."
    )
