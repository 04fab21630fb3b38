"""The frames (or landings) where one contact law acts alone, per signature: least-squares rows of a response on a
design (diagnosis.contact_signatures), from each body's per-frame quantities (diagnosis.contact_kinematics).

The floor's push, load and torque are per unit mass of what they act on, a free body or a whole tree of jointed bodies
(contact_kinematics): the ratios the rows read (friction and torques over the load) are the same either way.

Assumptions: a level floor at meta.floor_z with gravity along -z; vertices within contact_kinematics.TOUCH of the
lowest one carry the contact; the body is convex.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactbench.diagnosis.contact_kinematics import split_kinematics
from contactbench.diagnosis.phases import IMPACT_SPEED, SLIP_SPEED
from contactbench.scene import Recordings, Split

# Flat on a face (contact_kinematics.FLAT_ANGLE) and the body tilting slower than this at its edges
# (|w_horizontal| width / 2).
TILT_SPEED = 0.1  # m/s
# A step whose floor push exceeds this many g is an impact, not sliding, rolling or spinning.
IMPACT_LOAD = 3.0
# rad/s: spin (about the vertical) and roll (about the horizontal) that last through a step, so that friction acts
# kinetically: torsional friction at the library's reference (0.01 m) stops 0.36 rad/s per step at the load m g.
SPIN_SPEED = 0.3
ROLL_SPEED = 1.0
# rad/s: a sliding body whose spin is below this is held (static torsional friction keeps it from spinning up).
HELD_SPIN = 0.05
# Sliding steps further than this many robust standard deviations from one friction coefficient are bumps.
OUTLIER = 8.0
# A landing: the first contact after at least two frames of flight; the rebound is read over this many frames.
REBOUND_FRAMES = 3


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
    # beside the load, a regressor for a resistance that grows with the roll (contact_statistics.rolling_resistance)
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
    """Landings: the first frame in contact after two frames of flight (of the whole tree, for a body on joints), with
    the vertex lowest there approaching faster than IMPACT_SPEED in the frame before. Response: its rebound (the
    largest upward speed it reaches within REBOUND_FRAMES) over its approach speed; extras: approach speed and where
    it landed."""
    flying = k["flying"]
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
    for k in split_kinematics(dataset, split):
        parts["sliding"].append(sliding_rows(k))
        parts["spin"].append(spin_rows(k))
        parts["rolling"].append(rolling_rows(k))
        parts["landing"].append(landing_rows(k))
        held += held_counts(k)
    out = {name: Rows.concatenate(rows) for name, rows in parts.items()}
    out["sliding"] = _without_outliers(out["sliding"])
    out["held"] = held
    return out
