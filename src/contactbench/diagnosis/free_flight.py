"""A model-free first check: do bodies in free flight fall at meta.gravity, and does a drag slow them?

In free flight the centre of mass obeys x'' = g exactly (in vacuum), so the second difference of its recorded
positions over dt^2 measures the acceleration the recordings actually show, with no simulator and no fitted
parameter. It is fitted as a constant plus a quadratic drag, a = c - k |v| v. A fall c other than meta.gravity means
the recordings' time base or length scale is off (a true frame interval of sqrt(a / g) dt, or positions scaled by
a / g), or meta.gravity itself is wrong; MuJoCo can express all three as a scaled gravity (library effect
`gravity_scale`). A k above zero is drag (wind is drag in moving air): library effects `air_drag` / `wind`. Fit on
train, decide on val, confirm on test.

Bodies on joints fly as one system: the hinge force acts between them, so each one's centre of mass swings off the
parabola while the tree's mass-weighted centre of mass stays on it (the joint's forces cancel in the tree's total
momentum). A tree flies when every one of its bodies does, and gives one row per frame; a free body is a tree of one.
"""

from __future__ import annotations

import numpy as np

from contactbench import rotations
from contactbench.kinematics import world_vertices
from contactbench.scene import Recordings, Split
from contactbench.sim.bullet_scene import trees

SPLITS = ("train", "val", "test")
# A frame counts as free flight when, at it and at both neighbours, the body's lowest vertex is this fraction of its
# width above the floor (2 cm for the 10.5 cm real cube; contact and the tracker's filtering stay out of it) and no
# other body's bounding sphere comes within that distance of its own; for bodies on joints, every body of the tree
# (bodies of one tree may touch each other: their forces cancel in the tree's momentum).
CLEARANCE = 0.2
# The deviation must be at least this fraction of |meta.gravity| to count (the decision rule's practical margin).
MARGIN = 0.005
# A frame whose centre of mass falls at less than this fraction of |g| is held up by something (a floor higher or
# tilted against the recorded one, a neighbour), not flying: drag that strong would mean a terminal speed of a few
# m/s. (Strong synthetic drag stays well above it; a tilted floor leaves many "free" frames below it, the real cube
# almost none: docs/results/calibration.md.)
SUPPORTED = 0.5
# What free flight says of an effect that must show there (an apparent gravity, a drag): on val it is measured
# (beyond MARGIN, significant), ruled out (its whole interval within MARGIN of none), or inconclusive (neither: too
# few or too noisy free-flight frames to tell).
MEASURED, RULED_OUT, INCONCLUSIVE = "measured", "ruled out", "inconclusive"


def resample_weights(n_tosses: int, rng: np.random.Generator, bootstrap: int) -> np.ndarray:
    """[bootstrap + 1, n_tosses] how often each toss is drawn: row 0 every toss once (the point estimate), then the
    resamples (the frames of a toss count together)."""
    weights = np.zeros((bootstrap + 1, n_tosses))
    weights[0] = 1
    picks = rng.integers(0, n_tosses, size=(bootstrap, n_tosses))
    np.add.at(weights, (np.arange(1, bootstrap + 1)[:, None], picks), 1)
    return weights


def least_squares_by_toss(
    toss: np.ndarray, design: np.ndarray, response: np.ndarray, weights: np.ndarray, per_row: int = 1
) -> np.ndarray:
    """Least squares of `response` [R] on `design` [R, P] for every row of `weights` (resample_weights): [draws + 1,
    P]. Per toss the normal equations, so that a resample only weights them; `toss` [R / per_row] names the toss of
    each group of `per_row` consecutive rows (a frame's three axes)."""
    n_tosses, parameters = weights.shape[1], design.shape[1]
    owner = np.repeat(toss, per_row)
    normal, moment = np.zeros((n_tosses, parameters, parameters)), np.zeros((n_tosses, parameters))
    np.add.at(normal, owner, design[:, :, None] * design[:, None, :])
    np.add.at(moment, owner, design * response[:, None])
    return np.einsum("dij,dj->di", np.linalg.pinv(np.einsum("dn,nij->dij", weights, normal)), weights @ moment)


def systems(dataset: Recordings) -> list[tuple[int, ...]]:
    """The bodies that fly as one: each tree of jointed bodies (its root first), a free body alone, in the order of
    their roots."""
    return [(tree.root, *(dataset.joints[j].child for j in tree.joints)) for tree in trees(dataset)]


def free_frames(dataset: Recordings, split: Split) -> np.ndarray:
    """[N, T, K] True where body k's tree (body k alone if free) is in free flight (see CLEARANCE) at frames t-1, t
    and t+1 (False at the ends)."""
    poses = np.nan_to_num(split.poses)
    widths = dataset.widths()
    clear = np.zeros(poses.shape[:3], dtype=bool)
    radii = []
    for k in range(dataset.n_bodies):
        vertices = dataset.body_mesh(k).vertices
        radii.append(float(np.linalg.norm(vertices, axis=1).max()))
        lowest = world_vertices(poses[:, :, k], vertices)[..., 2].min(axis=-1) - dataset.floor_z
        clear[:, :, k] = lowest > CLEARANCE * widths[k]
    groups = systems(dataset)
    tree_of = {k: members for members in groups for k in members}
    for k in range(dataset.n_bodies):
        for j in range(dataset.n_bodies):
            if j not in tree_of[k]:
                gap = np.linalg.norm(poses[:, :, k, :3] - poses[:, :, j, :3], axis=-1) - radii[k] - radii[j]
                clear[:, :, k] &= gap > CLEARANCE * widths[k]
    clear &= split.valid_mask()[..., None]
    clear &= np.isfinite(split.poses).all(axis=-1)
    for members in groups:
        if len(members) > 1:
            clear[:, :, members] = clear[:, :, members].all(axis=-1, keepdims=True)
    free = np.zeros_like(clear)
    free[:, 1:-1] = clear[:, :-2] & clear[:, 1:-1] & clear[:, 2:]
    gravity = np.asarray(dataset.gravity, dtype=float)
    falling = system_motion(dataset, split)[1] @ gravity / float(gravity @ gravity)  # [N, T, S] in units of g
    for s, members in enumerate(groups):
        if len(members) == 1:
            free[:, :, members[0]] &= falling[:, :, s] >= SUPPORTED
        else:
            free[:, :, members] &= _supported_stretches(free[:, :, members[0]], falling[:, :, s])[..., None]
    return free


def _supported_stretches(free: np.ndarray, falling: np.ndarray) -> np.ndarray:
    """[N, T] the free frames [N, T] of the stretches of flight whose mean fall (in units of g) is SUPPORTED or more.

    A tree is judged stretch by stretch, not frame by frame: a frame's second difference carries the tracking noise
    of every body's pose, and cutting it on one side only biases the fall that is left (the real elbow's would come
    out well above g); a stretch's mean is the change of velocity across it, which that noise hardly moves. Free
    bodies keep the frame-by-frame rule their recordings were calibrated with."""
    starts = free & ~np.concatenate([np.zeros_like(free[:, :1]), free[:, :-1]], axis=1)
    stretch = np.cumsum(starts.reshape(-1)).reshape(free.shape) - 1  # each free frame's stretch
    count = int(starts.sum())
    totals, sizes = np.zeros(count), np.zeros(count)
    np.add.at(totals, stretch[free], falling[free])
    np.add.at(sizes, stretch[free], 1)
    kept = np.zeros_like(free)
    kept[free] = (totals / np.maximum(sizes, 1))[stretch[free]] >= SUPPORTED
    return kept


def centre_motion(dataset: Recordings, split: Split) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference velocities and accelerations of the centres of mass [N, T, K, 3] (zero at the ends)."""
    poses = np.nan_to_num(split.poses)
    centres = np.stack(
        [
            poses[:, :, k, :3] + rotations.rotate(poses[:, :, k, 3:], dataset.inertial(k)[0])
            for k in range(dataset.n_bodies)
        ],
        axis=2,
    )  # [N, T, K, 3]
    velocity, acceleration = np.zeros_like(centres), np.zeros_like(centres)
    velocity[:, 1:-1] = (centres[:, 2:] - centres[:, :-2]) / (2 * dataset.dt)
    acceleration[:, 1:-1] = (centres[:, 2:] - 2 * centres[:, 1:-1] + centres[:, :-2]) / dataset.dt**2
    return velocity, acceleration


def system_motion(dataset: Recordings, split: Split) -> tuple[np.ndarray, np.ndarray]:
    """Velocities and accelerations [N, T, S, 3] of each system's (`systems`) mass-weighted centre of mass, as
    centre_motion's; a free body's are its own, untouched."""
    velocity, acceleration = centre_motion(dataset, split)
    moving, falling = [], []
    for members in systems(dataset):
        if len(members) == 1:
            moving.append(velocity[:, :, members[0]])
            falling.append(acceleration[:, :, members[0]])
            continue
        masses = np.array([dataset.bodies[k].mass for k in members])
        share = masses / masses.sum()
        moving.append(np.einsum("k,ntki->nti", share, velocity[:, :, members]))
        falling.append(np.einsum("k,ntki->nti", share, acceleration[:, :, members]))
    return np.stack(moving, axis=2), np.stack(falling, axis=2)


def measure(dataset: Recordings, split: Split, rng: np.random.Generator, draws: int, confidence: float = 0.95) -> dict:
    """One split's free-flight accelerations as a constant plus a drag, a = c - k |v| v, fitted by least squares over
    every free-flight frame, with standard errors and percentile intervals from resampling trajectories (the frames of
    one toss count together). c is the fall net of the drag: drag shifts a plain mean (a strong drag makes a body fall
    measurably below g on average), c stays at g. And k times the median squared speed, the deceleration
    the drag causes at a typical speed. A tree of jointed bodies gives one row per frame, its centre of mass's."""
    free = free_frames(dataset, split)[:, :, [members[0] for members in systems(dataset)]]  # [N, T, S]
    velocity, acceleration = system_motion(dataset, split)
    used, rows = np.unique(np.nonzero(free)[0], return_inverse=True)  # the tosses that fly; each frame's toss
    if len(used) < 2:
        return {"n_trajectories": int(len(used)), "n_frames": int(free.sum())}
    # Per toss, the normal equations of the fit, so that a resample only weights them: unknowns c_x, c_y, c_z, k.
    v, a = velocity[free], acceleration[free]  # [F, 3]
    design = np.zeros((len(v), 3, 4))
    design[:, :, :3] = np.eye(3)
    design[:, :, 3] = -np.linalg.norm(v, axis=-1, keepdims=True) * v
    solved = least_squares_by_toss(
        rows, design.reshape(-1, 4), a.reshape(-1), resample_weights(len(used), rng, draws), per_row=3
    )  # [draws + 1, 4]
    point, samples = solved[0], solved[1:]
    tail = (1.0 - confidence) / 2 * 100
    ci = np.percentile(samples, [tail, 100 - tail], axis=0).T  # [4, 2]
    speed_squared = float(np.median(np.sum(v**2, axis=-1)))
    return {
        "n_trajectories": int(len(used)),
        "n_frames": int(free.sum()),
        "acceleration": point[:3].tolist(),
        "sem": samples[:, :3].std(axis=0).tolist(),
        "ci95": ci[:3].tolist(),  # [axis] -> [low, high]
        "drag_per_m": float(point[3]),
        "drag_ci95": ci[3].tolist(),
        "median_speed_m_s": speed_squared**0.5,
        "drag_deceleration_m_s2": float(point[3]) * speed_squared,
    }


def check(dataset: Recordings, rng: np.random.Generator, draws: int = 1000, confidence: float = 0.95) -> dict:
    """The free-flight findings (`measure` per split). The fall: the scale a/g along meta.gravity fitted on train;
    whether val says it differs from 1 (interval excludes it, by at least MARGIN); whether test confirms the same side.
    An apparent gravity where it differs and, on val, the fall has no part across gravity beyond MARGIN (a steady push
    sideways is a force: wind, or bodies counted as flying rest on a tilted floor), nothing pushes bodies along their
    motion (drag's interval below zero, by MARGIN: in free flight nothing can, so some "free" frames touch a floor
    sloping away and seem to fall slower), and it differs by more than the drag decelerates at a typical speed (what an
    error in the drag's form may shift the fall by). The drag: measured where on val its interval lies above zero and it
    decelerates by at least MARGIN of |meta.gravity| at a typical speed, confirmed where test's interval lies above zero
    too. Each is then MEASURED, RULED_OUT (val's interval of the fall within MARGIN of meta.gravity; of the drag's
    deceleration below MARGIN) or INCONCLUSIVE: `gravity_evidence`, `drag_evidence`."""
    gravity = np.asarray(dataset.gravity, dtype=float)
    g = float(np.linalg.norm(gravity))
    down = gravity / g
    splits = {
        name: measure(dataset, dataset.split(name), rng, draws, confidence) for name in SPLITS if name in dataset.splits
    }
    out: dict = {"meta_gravity": gravity.tolist(), "clearance_of_width": CLEARANCE, "margin": MARGIN, "splits": splits}
    for part in splits.values():
        if "acceleration" in part:
            part["along_gravity"] = float(np.dot(part["acceleration"], down))
            # along meta.gravity: the interval of the projection (gravity lies along an axis in practice)
            axis = int(np.argmax(np.abs(down)))
            part["along_gravity_ci95"] = sorted(float(np.sign(down[axis]) * c) for c in part["ci95"][axis])
            part["along_gravity_sem"] = float(part["sem"][axis])
            part["across_gravity_m_s2"] = float(np.linalg.norm(np.cross(part["acceleration"], down)))
            part["scale"] = part["along_gravity"] / g
    train, val, test = (splits.get(name, {}) for name in SPLITS)
    if not all("acceleration" in part for part in (train, val, test)):
        out.update(
            scale=None,
            differs=False,
            confirmed=False,
            drag_measured=False,
            gravity_evidence=INCONCLUSIVE,
            drag_evidence=INCONCLUSIVE,
            sentence="Too few free-flight frames in some split to measure the free-fall acceleration.",
        )
        return out
    scale = train["scale"]
    low, high = (c / g for c in val["along_gravity_ci95"])
    differs = bool((low > 1 or high < 1) and abs(val["scale"] - 1) >= MARGIN)
    test_low, test_high = (c / g for c in test["along_gravity_ci95"])
    confirmed = bool(differs and ((test_low > 1) if low > 1 else (test_high < 1)))
    drag_measured = bool(val["drag_ci95"][0] > 0 and val["drag_deceleration_m_s2"] >= MARGIN * g)
    pushed = bool(val["drag_ci95"][1] < 0 and -val["drag_deceleration_m_s2"] >= MARGIN * g)
    gravity_like = bool(
        val["across_gravity_m_s2"] < MARGIN * g
        and not pushed
        and abs(val["scale"] - 1) * g > abs(val["drag_deceleration_m_s2"])
    )
    speed_squared = val["median_speed_m_s"] ** 2
    out.update(
        apparent_gravity=differs and gravity_like,  # what the gravity_scale effect may lean on
        gravity_evidence=_evidence(differs and gravity_like, 1 - MARGIN <= low and high <= 1 + MARGIN),
        drag_evidence=_evidence(drag_measured, val["drag_ci95"][1] * speed_squared < MARGIN * g),
        scale=scale,
        frame_interval_factor=float(np.sqrt(scale)),  # the true frame interval / meta.dt, if the time base is off
        frame_rate=float(1.0 / (np.sqrt(scale) * dataset.dt)),
        length_scale=scale,  # recorded / true lengths, if the length scale is off
        differs=differs,
        confirmed=confirmed,
        drag_measured=drag_measured,
        drag_confirmed=bool(drag_measured and test["drag_ci95"][0] > 0),
    )
    out["sentence"] = sentence(out)
    return out


def sentence(found: dict) -> str:
    """The report's lines: the fall (net of the drag, mean ± SE per split vs meta, and what it means), then the drag."""
    return f"{fall_sentence(found)} {drag_sentence(found)}"


def fall_sentence(found: dict) -> str:
    g = float(np.linalg.norm(found["meta_gravity"]))
    parts = ", ".join(
        f"{name} {part['along_gravity']:.3f} ± {part['along_gravity_sem']:.3f}"
        for name, part in found["splits"].items()
    )
    head = f"Free-flight acceleration along gravity, net of drag (m/s², mean ± SE): {parts}; meta.gravity {g:.3f}"
    if not found["differs"]:
        return head + ": consistent with meta (val)."
    verdict = "confirmed on test" if found["confirmed"] else "NOT confirmed on test"
    val = found["splits"]["val"]
    across, drag = val["across_gravity_m_s2"], val["drag_deceleration_m_s2"]
    if not found["apparent_gravity"]:
        return (
            f"{head}: {found['scale']:.4f} × meta (train), differs on val, {verdict}; but not a gravity: on val it "
            f"points across gravity ({across:.3f} m/s²), or bodies are pushed along their motion (drag "
            f"{drag:.3f} m/s², below), or it differs by less than drag decelerates, so a force acts in free flight "
            f"(drag, wind) or bodies counted as flying touch something."
        )
    return (
        f"{head}: apparent gravity {found['scale']:.4f} × meta (train), differs on val, {verdict}, with nothing "
        f"across gravity ({across:.3f} m/s²). Either the true frame interval is "
        f"{found['frame_interval_factor']:.4f} × meta.dt ({found['frame_rate']:.1f} Hz), or lengths are recorded at "
        f"{found['length_scale']:.4f} × true, or "
        f"meta.gravity is wrong."
    )


def _evidence(measured: bool, ruled_out: bool) -> str:
    return MEASURED if measured else RULED_OUT if ruled_out else INCONCLUSIVE


def drag_sentence(found: dict) -> str:
    parts = ", ".join(
        f"{name} {part['drag_per_m']:.3f} [{part['drag_ci95'][0]:.3f}, {part['drag_ci95'][1]:.3f}]"
        for name, part in found["splits"].items()
    )
    val = found["splits"]["val"]
    head = (
        f"Drag in free flight, a = c - k|v|v (k in 1/m, 95% CI): {parts}; on val it decelerates by "
        f"{val['drag_deceleration_m_s2']:.3f} m/s² at the median speed {val['median_speed_m_s']:.2f} m/s"
    )
    if found["drag_evidence"] == RULED_OUT:
        return f"{head}: a drag is ruled out (its 95% interval decelerates by less than {MARGIN:.1%} of meta.gravity)."
    if not found["drag_measured"]:
        return f"{head}: no drag beyond {MARGIN:.1%} of meta.gravity is measured, nor ruled out (val)."
    verdict = "confirmed on test" if found["drag_confirmed"] else "NOT confirmed on test"
    return f"{head}: a drag (still or moving air) beyond {MARGIN:.1%} of meta.gravity, {verdict}."
