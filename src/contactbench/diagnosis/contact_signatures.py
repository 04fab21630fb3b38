"""Model-free contact signatures from recorded poses: friction by slip direction, speed and place; spin, roll, bounce.

Free flight (diagnosis.free_flight) reads gravity and drag off the recordings with no simulator; in contact the same
can be done where one frame's motion isolates one law. Each measurement below is a least-squares fit over the frames
of a split, with percentile intervals from resampling tosses (the frames of a toss count together), and its evidence
on val (confirmed on test) as in free flight: MEASURED, RULED_OUT or INCONCLUSIVE. A step is the motion from frame
t-1 to frame t: its acceleration (v_t - v_{t-1}) / dt is what the engine's forces did in it (exact for the recorded
post-step velocities of a semi-implicit engine); the floor's whole push is then m (a + g), its normal part the load N.

Assumptions: a level floor at meta.floor_z with gravity along -z; vertices within TOUCH of the lowest one carry the
contact; the body is convex. Margins are calibrated on PyBullet datasets with nothing concealed (see each margin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactbench import rotations
from contactbench.diagnosis.free_flight import (
    INCONCLUSIVE,
    MEASURED,
    RULED_OUT,
    least_squares_by_toss,
    resample_weights,
)
from contactbench.diagnosis.phases import CONTACT_HEIGHT, IMPACT_SPEED, SLIP_SPEED, recorded_velocities
from contactbench.recordings import Recordings, Split

SPLITS = ("train", "val", "test")
# Vertices within this fraction of the body width above the lowest one carry the contact (engines sink 5-10 mm and
# rock, so a resting face's vertices lie up to a few mm apart).
TOUCH = 0.02
# Flat on a face: the most downward face normal within this angle of -z, and the body tilting slower than
# TILT_SPEED at its edges (|w_horizontal| width / 2). Looser selections let tumbling in: with 10 degrees and 0.2 m/s
# a null cube's anisotropy amplitude rose from 0.004 to 0.03 and the fit's residual from 0.09 to 0.6 m/s^2.
FLAT_ANGLE = np.radians(6.0)
TILT_SPEED = 0.1  # m/s
# A step whose floor push exceeds this many g is an impact, not sliding, rolling or spinning.
IMPACT_LOAD = 3.0
# rad/s: spin (about the vertical) and roll (about the horizontal) that last through a step, so that friction acts
# kinetically: torsional friction at the library's reference (0.01 m) stops 0.36 rad/s per step at the load m g.
SPIN_SPEED = 0.3
ROLL_SPEED = 1.0
# rad/s: a sliding body whose spin is below this is held (static torsional friction keeps it from spinning up).
HELD_SPIN = 0.05
# Floor cells for the friction's (and the bounce's) dependence on position, in body widths; a cell counts with at
# least MIN_CELL_TOSSES tosses and MIN_CELL_FRAMES frames in it (fewer left a dodecahedron's cell fit singular).
FRICTION_CELL = 2.0
BOUNCE_CELL = 4.0
MIN_CELL_TOSSES = 5
MIN_CELL_FRAMES = 10
# Sliding steps further than this many robust standard deviations from one friction coefficient are bumps.
OUTLIER = 8.0
# A landing: the first contact after at least two frames of flight; the rebound is read over this many frames.
REBOUND_FRAMES = 3
# Fewer tosses than this with frames of a signature in a split: no interval is given (INCONCLUSIVE).
MIN_TOSSES = 20

# Practical margins, each above what PyBullet shows with nothing concealed (cubes seeds 0-4, octahedra and tetrahedra
# seeds 0-1, dodecahedra seeds 0-1, icosahedra seeds 0-1, truncated octahedron, rhombicuboctahedron; val intervals)
# and, where an effect shows there, below what the library's reference effects (strength 1) give:
# - anisotropy amplitude a of mu(theta) = mu0 (1 + a cos 2(theta - axis)): null cubes and octahedra within +-0.01
#   (intervals); a floor friction 1.5x (2x) larger along x than y gives 0.15-0.17 (0.21). 0.03: a ratio of 1.06.
ANISOTROPY_MARGIN = 0.03
# - relative change of mu over the central 80% of the slip speeds: nulls within +-0.02 (intervals); a viscous floor
#   (1.5 / s, 3 / s) +0.07 (+0.11).
SPEED_MARGIN = 0.05
# - spread of mu over floor cells, relative, debiased: nulls below 0.01 (intervals); a 0.4 m checkerboard of
#   frictions 0.5 and 0.3 gives 0.12 on val (not confirmed on test), of 0.5 and 0.425 0.04 (cells straddle tiles).
POSITION_MARGIN = 0.03
# - torsional and rolling resistance in metres (torque per unit load): nulls within +-0.002 pivoting on a vertex's
#   spin, 0.0003-0.0021 rolling; the reference effects give 0.0104 and 0.0097-0.0113. Rolling's margin is higher: a
#   viscous floor (1.5 / s) resists a dodecahedron's roll by 0.0035 m, drag and spin damping by up to 0.005 m.
SPIN_MARGIN = 0.003  # m
ROLLING_MARGIN = 0.005  # m
# - share of flat sliding frames whose spin is held below HELD_SPIN: nulls 0.04-0.18, the reference torsional
#   friction 0.69-0.85 (spin sticks at zero, so kinetic steps all but vanish).
HELD_MARGIN = 0.4
# - bounce ratio (rebound / approach speed of the landing vertex): its change over the central 80% of approach
#   speeds, nulls up to 0.2 (intervals up to 0.32: PyBullet's own bounce depends on the impact speed); its spread
#   over floor cells, nulls up to 0.07 (intervals up to 0.15). No effect of the generator changes either.
BOUNCE_SPEED_MARGIN = 0.3
BOUNCE_POSITION_MARGIN = 0.15

# What each signature speaks to: a library effect (diagnosis.library) or physics the library does not list.
SPEAKS_TO = {
    "anisotropy": "anisotropic_friction",
    "speed": "outside the library: friction that depends on the slip speed (Stribeck, a viscous floor)",
    "position": "outside the library: friction that depends on where on the floor (patches, tiles)",
    "spin": "torsional_friction",
    "rolling": "rolling_friction",
    "bounce_speed": "outside the library: a restitution that depends on the impact speed",
    "bounce_position": "outside the library: a restitution that depends on where on the floor",
}


@dataclass
class Rows:
    """Frames (or landings) of one signature in one split: the toss of each, a design and a response (least squares
    response ~ design @ coefficients), and anything else a statistic needs per row."""

    toss: np.ndarray  # [F]
    design: np.ndarray  # [F, P]
    response: np.ndarray  # [F]
    extra: dict

    @classmethod
    def concatenate(cls, parts: list[Rows]) -> Rows:
        keys = parts[0].extra.keys()
        return cls(
            np.concatenate([p.toss for p in parts]),
            np.concatenate([p.design for p in parts]),
            np.concatenate([p.response for p in parts]),
            {key: np.concatenate([p.extra[key] for p in parts]) for key in keys},
        )


def _steps(state: np.ndarray) -> np.ndarray:
    """[N, T] True where a condition holds at frame t and at t-1 (the whole step)."""
    out = np.zeros_like(state)
    out[:, 1:] = state[:, 1:] & state[:, :-1]
    return out


def _isolated(dataset: Recordings, body: int, poses: np.ndarray) -> np.ndarray:
    """[N, T] True where no other body's bounding sphere comes within the contact height of this one's."""
    radii = [float(np.linalg.norm(dataset.body_mesh(k).vertices, axis=1).max()) for k in range(dataset.n_bodies)]
    clear = np.ones(poses.shape[:2], dtype=bool)
    for other in range(dataset.n_bodies):
        if other != body:
            gap = np.linalg.norm(poses[:, :, body, :3] - poses[:, :, other, :3], axis=-1)
            clear &= gap - radii[body] - radii[other] > CONTACT_HEIGHT * dataset.widths()[body]
    return clear


def body_kinematics(dataset: Recordings, split: Split, body: int) -> dict[str, np.ndarray]:
    """One body's per-frame quantities [N, T, ...]: the contact geometry at frame t and the step into it."""
    all_poses = np.nan_to_num(split.poses)
    poses = all_poses[:, :, body]
    velocities = np.nan_to_num(recorded_velocities(split, dataset.dt)[:, :, body])
    mesh = dataset.body_mesh(body)
    width = float(dataset.widths()[body])
    com, inertia = dataset.inertial(body)
    mass = dataset.bodies[body].mass
    g = float(np.linalg.norm(dataset.gravity))
    rotation = rotations.to_matrix(poses[..., 3:])  # [N, T, 3, 3]
    centre = poses[..., :3] + np.einsum("ntij,j->nti", rotation, com)
    vertices = poses[..., None, :3] + np.einsum("ntij,vj->ntvi", rotation, mesh.vertices)
    heights = vertices[..., 2] - dataset.floor_z
    lowest = heights.min(axis=-1)
    omega = velocities[..., 3:]
    velocity = velocities[..., :3] + np.cross(omega, centre - poses[..., :3])  # of the centre of mass
    arms = vertices - centre[..., None, :]
    vertex_velocity = velocity[..., None, :] + np.cross(omega[..., None, :], arms)
    corners = [mesh.vertices[mesh.faces[:, i]] for i in range(3)]
    normals = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # cosine of the angle between the most downward face normal and -z: 1 when a face lies flat on the floor
    flatness = -np.einsum("nti,fi->ntf", rotation[..., 2, :], normals).min(axis=-1)
    world_inertia = np.einsum("ntij,jk,ntlk->ntil", rotation, inertia, rotation)
    acceleration, angular_acceleration = np.zeros_like(velocity), np.zeros_like(omega)
    acceleration[:, 1:] = (velocity[:, 1:] - velocity[:, :-1]) / dataset.dt
    angular_acceleration[:, 1:] = (omega[:, 1:] - omega[:, :-1]) / dataset.dt
    # the torque about the centre of mass that the floor exerted in the step (Euler's equations, world frame)
    torque = np.einsum("ntij,ntj->nti", world_inertia, angular_acceleration) + np.cross(
        omega, np.einsum("ntij,ntj->nti", world_inertia, omega)
    )
    push = acceleration + np.array([0.0, 0.0, g])  # the floor's force per unit mass
    touching = heights < lowest[..., None] + TOUCH * width
    valid = split.valid_mask() & np.isfinite(split.poses[:, :, body]).all(axis=-1)
    valid &= _isolated(dataset, body, all_poses)
    return {
        "width": np.array(width),
        "g": np.array(g),
        "valid": valid,
        "in_contact": valid & (lowest < CONTACT_HEIGHT * width),
        "centre": centre,
        "touching": touching,
        "flat": flatness > np.cos(FLAT_ANGLE),
        "tilt_speed": np.linalg.norm(omega[..., :2], axis=-1) * width / 2,
        "arms": arms,
        "vertex_velocity": vertex_velocity,
        "omega": omega,
        "push": push,
        "load": push[..., 2],
        "torque_per_mass": torque / mass,
    }


def _slips(k: dict) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal slip speed of every vertex [N, T, V], and the least among the touching ones [N, T]."""
    slip = np.linalg.norm(k["vertex_velocity"][..., :2], axis=-1)
    return slip, np.where(k["touching"], slip, np.inf).min(axis=-1)


def _supported(k: dict) -> np.ndarray:
    """In contact, pressed by the floor and no impact."""
    return k["in_contact"] & (k["load"] > 0) & (k["load"] < IMPACT_LOAD * k["g"])


def _sliding_flat(k: dict) -> np.ndarray:
    """[N, T] a face on the floor, every touching vertex slipping, little tilting, no impact."""
    _, least = _slips(k)
    return _supported(k) & k["flat"] & (k["tilt_speed"] < TILT_SPEED) & (least > SLIP_SPEED)


def sliding_rows(k: dict) -> Rows:
    """Flat sliding steps (_sliding_flat at both ends). Coulomb friction pushes against the mean slip direction d of
    the touching vertices with mu N |d| (|d| < 1 where the body also spins), so the deceleration along d over the load
    is mu: response -a . d_hat, design N/m |d| (the statistics multiply the design by functions of the slip direction,
    speed and position)."""
    slip, _ = _slips(k)
    step = _steps(_sliding_flat(k))
    touching = k["touching"][step]
    units = k["vertex_velocity"][step][..., :2] / np.maximum(slip[step], 1e-12)[..., None]
    mean = (units * touching[..., None]).sum(axis=-2) / touching.sum(axis=-1, keepdims=True)
    size = np.linalg.norm(mean, axis=-1)
    keep = size > 0.1  # a body spinning about a point inside its face has no slip direction
    direction = mean[keep] / size[keep, None]
    response = -np.einsum("fi,fi->f", k["push"][step][keep, :2], direction)
    design = (k["load"][step][keep] * size[keep])[:, None]
    speed = (slip[step] * touching).sum(axis=-1) / touching.sum(axis=-1)
    return Rows(
        np.nonzero(step)[0][keep],
        design,
        response,
        {
            "angle": np.arctan2(direction[:, 1], direction[:, 0]),
            "speed": speed[keep],
            "position": k["centre"][step][keep, :2],
        },
    )


def spin_rows(k: dict) -> Rows:
    """Steps pivoting on one vertex while spinning about the vertical (the same sign and above SPIN_SPEED at both
    ends, so any torsional friction acts kinetically throughout). The floor's forces all act at that vertex, so
    their torque about it has no vertical part, whatever the friction: what remains is a couple about the contact
    normal, torsional friction. Response: that couple against the spin, per unit mass; design N/m; coefficient: the
    torsional friction in metres. (On faces and edges Coulomb friction's own spin torque depends on how the load
    spreads over the contact points, which the poses do not tell.)"""
    spin = k["omega"][..., 2]
    state = _supported(k) & (k["touching"].sum(axis=-1) == 1) & (np.abs(spin) > SPIN_SPEED)
    step = _steps(state)
    step[:, 1:] &= np.sign(spin[:, 1:]) == np.sign(spin[:, :-1])
    about_contact = _torque_about_touching(k)[step]
    return Rows(
        np.nonzero(step)[0],
        k["load"][step][:, None],
        -about_contact[:, 2] * np.sign(spin[step]),
        {},
    )


def held_counts(k: dict) -> np.ndarray:
    """Per toss [N, 2]: flat sliding frames whose spin is held below HELD_SPIN, and all flat sliding frames."""
    sliding = _sliding_flat(k)
    held = sliding & (np.abs(k["omega"][..., 2]) < HELD_SPIN)
    return np.stack([held.sum(axis=1), sliding.sum(axis=1)], axis=-1).astype(float)


def rolling_rows(k: dict) -> Rows:
    """Steps rolling over an edge or a vertex: at most two touching vertices, none slipping, the roll (horizontal
    angular velocity) above ROLL_SPEED, no impact, not flat. About the touching vertices' centre the floor's point
    forces have no torque along the edge, the rolling axis, so what opposes the roll there is rolling resistance:
    response the torque about that centre against the roll, per unit mass; design N/m; coefficient in metres."""
    slip, _ = _slips(k)
    roll = np.linalg.norm(k["omega"][..., :2], axis=-1)
    slipping = np.where(k["touching"], slip, 0.0).max(axis=-1)
    state = _supported(k) & ~k["flat"] & (k["touching"].sum(axis=-1) <= 2) & (slipping < SLIP_SPEED)
    step = _steps(state & (roll > ROLL_SPEED))
    about_contact = _torque_about_touching(k)[step]
    axis = k["omega"][step][:, :2] / roll[step][:, None]
    # beside the load, a regressor for a resistance that grows with the roll (see _rolling)
    return Rows(
        np.nonzero(step)[0],
        np.stack([k["load"][step], roll[step] * k["width"] ** 2], axis=-1),
        -np.einsum("fi,fi->f", about_contact[:, :2], axis),
        {},
    )


def _torque_about_touching(k: dict) -> np.ndarray:
    """[N, T, 3] the floor's torque per unit mass about the centroid of the touching vertices."""
    touching = k["touching"]
    centroid = (k["arms"] * touching[..., None]).sum(axis=-2) / touching.sum(axis=-1)[..., None]
    return k["torque_per_mass"] - np.cross(centroid, k["push"])


def landing_rows(k: dict) -> Rows:
    """Landings: the first frame in contact after two frames of flight, with the vertex lowest there approaching
    faster than IMPACT_SPEED in the frame before. Response: its rebound (the largest upward speed it reaches within
    REBOUND_FRAMES) over its approach speed; extras: approach speed and where it landed."""
    flying = k["valid"] & ~k["in_contact"]
    landing = np.zeros_like(flying)
    landing[:, 2:] = k["in_contact"][:, 2:] & flying[:, 1:-1] & flying[:, :-2]
    tosses, frames = np.nonzero(landing)
    frames_total = flying.shape[1]
    keep = frames + REBOUND_FRAMES <= frames_total
    tosses, frames = tosses[keep], frames[keep]
    vertex = np.argmin(k["arms"][tosses, frames][..., 2], axis=-1)
    vertical = k["vertex_velocity"][..., 2]
    approach = -vertical[tosses, frames - 1, vertex]
    window = frames[:, None] + np.arange(REBOUND_FRAMES)[None, :]
    rebound = vertical[tosses[:, None], window, vertex[:, None]].max(axis=1)
    inside = k["valid"][tosses[:, None], window].all(axis=1)
    keep = (approach > IMPACT_SPEED) & inside
    return Rows(
        tosses[keep],
        np.ones((int(keep.sum()), 1)),
        rebound[keep] / approach[keep],
        {"speed": approach[keep], "position": k["centre"][tosses[keep], frames[keep], :2]},
    )


def _without_outliers(rows: Rows) -> Rows:
    """The rows whose residual from one plain friction coefficient lies within OUTLIER robust standard deviations
    (1.4826 median absolute deviations): steps that bump over something (a seam in the floor, a tracking glitch)
    decelerate by several g for a frame."""
    if len(rows.toss) == 0:
        return rows
    design = rows.design[:, 0]
    residual = rows.response - design * np.median(rows.response / design)
    spread = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    keep = np.abs(residual - np.median(residual)) <= OUTLIER * spread
    return Rows(rows.toss[keep], rows.design[keep], rows.response[keep], {k: v[keep] for k, v in rows.extra.items()})


def split_rows(dataset: Recordings, split: Split) -> dict:
    """Every signature's rows over all bodies of one split (frames of all bodies in a toss count as that toss)."""
    n = split.n_trajectories
    parts: dict[str, list] = {"sliding": [], "spin": [], "rolling": [], "landing": []}
    held = np.zeros((n, 2))
    for body in range(dataset.n_bodies):
        k = body_kinematics(dataset, split, body)
        parts["sliding"].append(sliding_rows(k))
        parts["spin"].append(spin_rows(k))
        parts["rolling"].append(rolling_rows(k))
        parts["landing"].append(landing_rows(k))
        held += held_counts(k)
    out = {name: Rows.concatenate(rows) for name, rows in parts.items()}
    out["sliding"] = _without_outliers(out["sliding"])
    out["held"] = held
    return out


# ---------------------------------------------------------------- fits with resampled tosses


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


def _speed_change(rows: Rows, weights: np.ndarray, confidence: float, relative: bool) -> dict:
    """A quantity linear in the speed, q = q0 + q1 (s - s_median): its change q1 (s90 - s10) over the central 80% of
    the speeds, relative to q0 where `relative`."""
    speed = rows.extra["speed"]
    low, middle, high = np.percentile(speed, [10, 50, 90])
    design = _with_direction(rows, rows.design * np.stack([np.ones_like(speed), speed - middle], axis=-1))
    coefficients = fit(rows, design, weights)
    change = coefficients[:, 1] * (high - low) / (coefficients[:, 0] if relative else 1.0)
    return _summary(change, confidence, rows, speeds_m_s=[float(low), float(high)], at_median=float(coefficients[0, 0]))


def _cell_spread(rows: Rows, weights: np.ndarray, confidence: float, cell: float, relative: bool) -> dict:
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


def _coefficient(rows: Rows, weights: np.ndarray, confidence: float) -> dict:
    """The first coefficient of the rows' own design."""
    return _summary(fit(rows, rows.design, weights)[:, 0], confidence, rows)


def _rolling(rows: Rows, weights: np.ndarray, confidence: float) -> dict:
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


def measure_split(dataset: Recordings, split: Split, rng: np.random.Generator, bootstrap: int, confidence: float):
    """Every signature's statistic in one split (value, interval, counts); a signature with frames from fewer than
    MIN_TOSSES tosses gets counts only."""
    rows = split_rows(dataset, split)
    weights = resample_weights(split.n_trajectories, rng, bootstrap)
    width = float(dataset.widths().max())
    sliding, landing = rows["sliding"], rows["landing"]
    statistics = {
        "anisotropy": (sliding, lambda: anisotropy(sliding, weights, confidence)),
        "speed": (sliding, lambda: _speed_change(sliding, weights, confidence, relative=True)),
        "position": (sliding, lambda: _cell_spread(sliding, weights, confidence, FRICTION_CELL * width, True)),
        "spin": (rows["spin"], lambda: _coefficient(rows["spin"], weights, confidence)),
        "rolling": (rows["rolling"], lambda: _rolling(rows["rolling"], weights, confidence)),
        "bounce": (landing, lambda: _coefficient(landing, weights, confidence)),
        "bounce_speed": (landing, lambda: _speed_change(landing, weights, confidence, relative=False)),
        "bounce_position": (landing, lambda: _cell_spread(landing, weights, confidence, BOUNCE_CELL * width, False)),
    }
    out = {}
    for name, (part, statistic) in statistics.items():
        tosses = len(np.unique(part.toss))
        out[name] = statistic() if tosses >= MIN_TOSSES else {"n_tosses": tosses, "n_frames": len(part.toss)}
    out["spin_held"] = held_share(rows["held"], weights, confidence)
    return out


# ---------------------------------------------------------------- evidence


def evidence(val: dict, test: dict, margin: float, two_sided: bool = True) -> tuple[str, bool]:
    """MEASURED: val's interval lies beyond the margin (on one side), and test confirms where it has an interval (its
    estimate beyond the margin on that side, its interval clear of zero); RULED_OUT: val's interval within the margin;
    else INCONCLUSIVE. Also whether test confirmed."""
    if "ci" not in val:
        return INCONCLUSIVE, False
    low, high = val["ci"]
    above, below = low > margin, two_sided and high < -margin
    if above or below:
        if "ci" not in test:
            return MEASURED, False
        if above:
            confirmed = bool(test["value"] > margin and test["ci"][0] > 0)
        else:
            confirmed = bool(test["value"] < -margin and test["ci"][1] < 0)
        return (MEASURED if confirmed else INCONCLUSIVE), confirmed
    # A debiased size far below zero is noise that swamps it: not ruled out.
    return (RULED_OUT if -margin < low and high < margin else INCONCLUSIVE), False


MARGINS = {
    "anisotropy": ANISOTROPY_MARGIN,
    "speed": SPEED_MARGIN,
    "position": POSITION_MARGIN,
    "spin": SPIN_MARGIN,
    "spin_held": HELD_MARGIN,
    "rolling": ROLLING_MARGIN,
    "bounce_speed": BOUNCE_SPEED_MARGIN,
    "bounce_position": BOUNCE_POSITION_MARGIN,
}
# Sizes that cannot be negative but for noise (amplitudes, spreads, shares): only their upper side is measured.
ONE_SIDED = ("anisotropy", "position", "spin_held", "bounce_position")


def measure(dataset: Recordings, rng: np.random.Generator, bootstrap: int = 1000, confidence: float = 0.95) -> dict:
    """The contact signatures per split and their evidence on val, confirmed on test: `signatures[name]` holds the
    evidence, the margin, what it speaks to and a sentence for the report; `evidence` maps library effects
    (anisotropic_friction, torsional_friction, rolling_friction) to MEASURED / RULED_OUT / INCONCLUSIVE. The spin
    evidence joins two statistics: the torsional friction read off kinetic steps, and the share of sliding frames
    whose spin is held at zero (strong torsional friction leaves hardly any kinetic steps)."""
    splits = {
        name: measure_split(dataset, dataset.split(name), rng, bootstrap, confidence)
        for name in SPLITS
        if name in dataset.splits
    }
    val, test = splits.get("val", {}), splits.get("test", {})
    signatures = {}
    for name, margin in MARGINS.items():
        state, confirmed = evidence(val.get(name, {}), test.get(name, {}), margin, name not in ONE_SIDED)
        signatures[name] = {"evidence": state, "confirmed": confirmed, "margin": margin}
    rolling = signatures["rolling"]
    if rolling["evidence"] == MEASURED and val["rolling"]["beside_viscous_ci"][0] <= ROLLING_MARGIN:
        # it grows with the roll's speed: a force at the centre (a viscous floor, drag) or a spin damping, which
        # resist rolling about the contact too, rather than rolling friction
        rolling.update(evidence=INCONCLUSIVE, confirmed=False, viscous=True)
    kinetic, held = signatures.pop("spin"), signatures.pop("spin_held")
    # Either statistic may lack frames (few flat slides on many-faced bodies; few kinetic steps where strong
    # torsional friction holds the spin): one that rules it out then decides, unless the other is noisy.
    states = [
        found["evidence"] for found, name in ((kinetic, "spin"), (held, "spin_held")) if "ci" in val.get(name, {})
    ]
    if MEASURED in states:
        spin_state = MEASURED
    elif states and all(state == RULED_OUT for state in states):
        spin_state = RULED_OUT
    else:
        spin_state = INCONCLUSIVE
    signatures["spin"] = {
        "evidence": spin_state,
        "confirmed": kinetic["confirmed"] or held["confirmed"],
        "margin": SPIN_MARGIN,
        "held_margin": HELD_MARGIN,
        "kinetic_evidence": kinetic["evidence"],
        "held_evidence": held["evidence"],
    }
    for name, found in signatures.items():
        found["speaks_to"] = SPEAKS_TO[name]
        found["confidence"] = confidence
        found["sentence"] = SENTENCES[name](splits, found)
    return {
        "confidence": confidence,
        "splits": splits,
        "signatures": signatures,
        "evidence": {
            "anisotropic_friction": signatures["anisotropy"]["evidence"],
            "torsional_friction": signatures["spin"]["evidence"],
            "rolling_friction": signatures["rolling"]["evidence"],
        },
    }


# ---------------------------------------------------------------- sentences


def _values(splits: dict, name: str, digits: int, unit: str = "") -> str:
    parts = []
    for split, found in splits.items():
        part = found.get(name, {})
        if "ci" in part:
            low, high = part["ci"]
            parts.append(f"{split} {part['value']:.{digits}f}{unit} [{low:.{digits}f}, {high:.{digits}f}]")
        else:
            parts.append(f"{split} too few ({part.get('n_tosses', 0)} tosses)")
    return ", ".join(parts)


def _ci(found: dict) -> str:
    return f"{found['confidence']:.0%} CI"


def _verdict(found: dict, what: str, margin: str) -> str:
    speaks = found["speaks_to"]
    about = f"library effect {speaks}" if "outside" not in speaks else speaks.split(": ", 1)[1]
    if found["evidence"] == MEASURED:
        tail = "confirmed on test" if found["confirmed"] else "test has too few frames to confirm"
        return f"{what} beyond {margin} (val), {tail}: evidence for {about}."
    if found["evidence"] == RULED_OUT:
        return f"{what} ruled out: val's interval lies within {margin} ({about})."
    return f"{what}: neither measured nor ruled out at {margin} (val, or not confirmed on test)."


def _anisotropy_sentence(splits: dict, found: dict) -> str:
    val = splits.get("val", {}).get("anisotropy", {})
    extra = (
        f"; on val mu0 {val['mu0']:.3f}, the largest friction along {val['axis_deg']:.0f} deg (max/min "
        f"{val['ratio']:.2f})"
        if "ci" in val
        else ""
    )
    return (
        f"Sliding friction against the slip direction, mu = mu0 (1 + A cos 2(theta - axis)), A debiased ({_ci(found)}, "
        f"flat sliding steps): {_values(splits, 'anisotropy', 3)}{extra}. "
        + _verdict(found, "An anisotropic floor friction", f"A = {ANISOTROPY_MARGIN}")
    )


def _speed_sentence(splits: dict, found: dict) -> str:
    return (
        "Sliding friction against slip speed, relative change of mu over the central 80% of speeds "
        f"({_ci(found)}): {_values(splits, 'speed', 3)}. "
        + _verdict(found, "A friction that changes with speed", f"{SPEED_MARGIN:.0%} of mu")
        + " (Air drag shows here too; free flight tells it apart.)"
    )


def _position_sentence(splits: dict, found: dict) -> str:
    return (
        f"Sliding friction against floor position, spread of mu over {FRICTION_CELL:g}-width cells relative to its "
        f"mean, debiased ({_ci(found)}): {_values(splits, 'position', 3)}. "
        + _verdict(found, "A friction that varies over the floor", f"{POSITION_MARGIN:.0%} of mu")
    )


def _spin_sentence(splits: dict, found: dict) -> str:
    head = (
        "Spin decay: torsional friction (spin torque per load, m) while pivoting on one vertex, where Coulomb "
        f"friction has no spin torque ({_ci(found)}): {_values(splits, 'spin', 4, ' m')}; share of flat sliding frames "
        f"whose spin is held below {HELD_SPIN} rad/s: {_values(splits, 'spin_held', 2)}. "
    )
    if found["evidence"] == MEASURED:
        tail = "confirmed on test" if found["confirmed"] else "test has too few frames to confirm"
        return (
            f"{head}A torsional friction: the torque beyond {SPIN_MARGIN * 1000:g} mm, or spin held in over "
            f"{HELD_MARGIN:.0%} of sliding frames (val), {tail}: evidence for library effect torsional_friction."
        )
    if found["evidence"] == RULED_OUT:
        return (
            f"{head}A torsional friction ruled out: val's torque within {SPIN_MARGIN * 1000:g} mm and spin held in "
            f"under {HELD_MARGIN:.0%} of sliding frames, where measured (library effect torsional_friction)."
        )
    return f"{head}A torsional friction: neither measured nor ruled out (val, or not confirmed on test)."


def _rolling_sentence(splits: dict, found: dict) -> str:
    head = (
        "Rolling decay: rolling resistance (torque against the roll per load about the touching edge or vertex, "
        f"m; {_ci(found)}): {_values(splits, 'rolling', 4, ' m')}. "
    )
    if found.get("viscous"):
        return (
            f"{head}It exceeds {ROLLING_MARGIN * 1000:g} mm but grows with the roll's speed: a force at the centre (a "
            "viscous floor, drag) or a spin damping, not rolling friction; inconclusive for rolling_friction."
        )
    return head + _verdict(found, "A rolling resistance", f"{ROLLING_MARGIN * 1000:g} mm")


def _bounce_speed_sentence(splits: dict, found: dict) -> str:
    return (
        f"Bounce ratio at landings (rebound / approach speed of the landing vertex; {_ci(found)}): "
        f"{_values(splits, 'bounce', 3)}; its change over the central 80% of approach speeds: "
        f"{_values(splits, 'bounce_speed', 3)}. "
        + _verdict(found, "A bounce that depends on the impact speed", f"{BOUNCE_SPEED_MARGIN:g}")
    )


def _bounce_position_sentence(splits: dict, found: dict) -> str:
    return (
        f"Bounce ratio against floor position, spread over {BOUNCE_CELL:g}-width cells, debiased "
        f"({_ci(found)}): {_values(splits, 'bounce_position', 3)}. "
        + _verdict(found, "A bounce that varies over the floor", f"{BOUNCE_POSITION_MARGIN:g}")
    )


SENTENCES = {
    "anisotropy": _anisotropy_sentence,
    "speed": _speed_sentence,
    "position": _position_sentence,
    "spin": _spin_sentence,
    "rolling": _rolling_sentence,
    "bounce_speed": _bounce_speed_sentence,
    "bounce_position": _bounce_position_sentence,
}
