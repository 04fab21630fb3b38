"""The residual model's step: SysID'd MuJoCo steps every trajectory at once, then a learned impulse corrects each body.

States are MuJoCo free-joint states per body: qpos [..., K, 7] (x y z qw qx qy qz) and qvel [..., K, 6] (world
linear velocity of the mesh-frame origin, BODY-frame angular velocity). A correction is a velocity change per body
[..., K, 6] (linear part in the body frame of the post-step pose, angular part body-frame), added to MuJoCo's
post-step velocity and integrated over the same frame (x += dt dv): an extra impulse inside the step, which keeps the
semi-implicit convention the recordings follow (x_t - x_{t-1} = dt v_t).

Penetration: a correction is a projection away from the floor's inside. For every body, the vertices within
`contact_margin` of the floor after MuJoCo's step must not move down faster after the correction than MuJoCo moved
them (nor move down at all if MuJoCo had them rising); the whole body's correction is scaled down until that holds.
What remains between bodies is MuJoCo's to resolve: the next step's contact solver sees the corrected velocities.
Energy: a correction never leaves a body with more kinetic energy than it had before or after MuJoCo's step (scaled
down until it does), so a learned impulse cannot feed a rollout energy from nowhere.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from contactbench import rotations
from contactbench.errors import NotApplicable
from contactbench.kinematics import world_vertices
from contactbench.scene import Scene
from contactbench.sim.rollout import kinetic_energies

LOWEST_VERTICES = 4  # the body's vertices nearest the floor that the features describe (a tetrahedron has four)
NEIGHBOUR_FEATURES = 7  # relative position and velocity of the nearest other body (body frame), and its distance
Predictor = Callable[[np.ndarray], np.ndarray]  # features [M, F] -> body-frame velocity corrections [M, 6]
STEP_CHANGE = slice(10, 16)  # the columns of `features` that describe MuJoCo's step (the rest: the state before it)


@dataclass(frozen=True)
class Bodies:
    """What the correction needs to know of a scene: mesh vertices, mass properties, floor, gravity, frame time."""

    vertices: tuple[np.ndarray, ...]  # per body [V_k, 3], mesh frame
    masses: np.ndarray  # [K] kg
    com: np.ndarray  # [K, 3] centre of mass, mesh frame
    inertia: np.ndarray  # [K, 3, 3] about the centre of mass, mesh axes
    floor_z: float
    gravity: np.ndarray  # [3]
    dt: float

    @classmethod
    def of(cls, dataset: Scene) -> Bodies:
        if dataset.static or dataset.joints:
            raise NotApplicable(
                f"the residual correction is projected against the flat floor, body by body; {dataset.name} has "
                "terrain or joints"
            )
        properties = [dataset.inertial(k) for k in range(dataset.n_bodies)]
        return cls(
            vertices=tuple(np.asarray(dataset.body_mesh(k).vertices, dtype=float) for k in range(dataset.n_bodies)),
            masses=np.array([body.mass for body in dataset.bodies], dtype=float),
            com=np.stack([com for com, _ in properties]),
            inertia=np.stack([inertia for _, inertia in properties]),
            floor_z=float(dataset.floor_z),
            gravity=np.asarray(dataset.gravity, dtype=float),
            dt=float(dataset.dt),
        )

    @property
    def n_bodies(self) -> int:
        return len(self.vertices)

    @property
    def n_features(self) -> int:
        return 3 + 1 + 6 + 6 + 5 * LOWEST_VERTICES + NEIGHBOUR_FEATURES


def _to_body(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return rotations.rotate(rotations.conjugate(q), v)


def vertical_velocities(qpos: np.ndarray, qvel: np.ndarray, offset_world: np.ndarray) -> np.ndarray:
    """World vertical velocity [..., M, V] of points at world offsets [..., V, 3] from the body origin, for M body
    velocities qvel [..., M, 6] at once (one rotation for all of them; only the z of v + w x r is ever used)."""
    omega = rotations.rotate(qpos[..., None, 3:], qvel[..., 3:])  # [..., M, 3]
    turning = omega[..., None, 0] * offset_world[..., None, :, 1] - omega[..., None, 1] * offset_world[..., None, :, 0]
    return qvel[..., None, 2] + turning


def features(bodies: Bodies, qpos0: np.ndarray, qvel0: np.ndarray, qpos1: np.ndarray, qvel1: np.ndarray) -> np.ndarray:
    """Per-body features [..., K, F] of one MuJoCo step from (qpos0, qvel0) to (qpos1, qvel1), in the body frame of
    the pre-step pose: gravity's direction, height above the floor, velocity, MuJoCo's velocity change over the step,
    the lowest vertices (height, vertical velocity, mesh-frame position) and the nearest other body."""
    q0 = qpos0[..., 3:]
    gravity = np.broadcast_to(bodies.gravity / np.linalg.norm(bodies.gravity), q0.shape[:-1] + (3,))
    # Gravity, velocity and velocity change turned in one pass: a rollout calls this every frame, where numpy's
    # per-call cost outweighs the arithmetic (the rotation is element-wise: the same numbers as one by one).
    turned = _to_body(q0[..., None, :], np.stack([gravity, qvel0[..., :3], qvel1[..., :3] - qvel0[..., :3]], axis=-2))
    parts = [
        turned[..., 0, :],
        qpos0[..., 2:3] - bodies.floor_z,
        turned[..., 1, :],
        qvel0[..., 3:],
        turned[..., 2, :],
        qvel1[..., 3:] - qvel0[..., 3:],
        _lowest_vertices(bodies, qpos0, qvel0),
        _nearest_neighbour(qpos0, qvel0),
    ]
    return np.concatenate(parts, axis=-1)


def _lowest_vertices(bodies: Bodies, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    out = []
    for k, vertices in enumerate(bodies.vertices):
        placed = world_vertices(qpos[..., k, :], vertices)  # [..., V, 3]
        order = np.argsort(placed[..., 2], axis=-1)[..., :LOWEST_VERTICES]
        lowest = np.take_along_axis(placed, order[..., None], axis=-2)
        vertical = vertical_velocities(qpos[..., k, :], qvel[..., k, None, :], lowest - qpos[..., k, None, :3])
        out.append(
            np.concatenate(
                [lowest[..., 2] - bodies.floor_z, vertical[..., 0, :], vertices[order].reshape(*order.shape[:-1], -1)],
                axis=-1,
            )
        )
    return np.stack(out, axis=-2)


def _nearest_neighbour(qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    n_bodies = qpos.shape[-2]
    out = np.zeros(qpos.shape[:-1] + (NEIGHBOUR_FEATURES,))
    if n_bodies < 2:
        return out
    position = qpos[..., :3]
    distance = np.linalg.norm(position[..., :, None, :] - position[..., None, :, :], axis=-1)
    distance[..., np.arange(n_bodies), np.arange(n_bodies)] = np.inf
    nearest = np.argmin(distance, axis=-1)  # [..., K]
    other_position = np.take_along_axis(position, nearest[..., None], axis=-2)
    other_velocity = np.take_along_axis(qvel[..., :3], nearest[..., None], axis=-2)
    q = qpos[..., 3:]
    out[..., 0:3] = _to_body(q, other_position - position)
    out[..., 3:6] = _to_body(q, other_velocity - qvel[..., :3])
    out[..., 6] = np.take_along_axis(distance, nearest[..., None], axis=-1)[..., 0]
    return out


def targets(
    qpos0: np.ndarray, qpos1: np.ndarray, qvel1: np.ndarray, recorded_next: np.ndarray, dt: float
) -> np.ndarray:
    """The correction [..., K, 6] that puts MuJoCo's step from qpos0 onto the recorded next pose [..., K, 7]: the
    velocity change whose integration over the frame moves qpos1 there (linear part in qpos1's body frame)."""
    linear = (recorded_next[..., :3] - qpos1[..., :3]) / dt
    turn = rotations.multiply(rotations.conjugate(qpos0[..., 3:]), rotations.normalize(recorded_next[..., 3:]))
    angular = rotations.to_rotation_vector(turn) / dt  # body frame of qpos0, as MuJoCo integrates q0 (x) exp(dt w)
    return np.concatenate([_to_body(qpos1[..., 3:], linear), angular - qvel1[..., 3:]], axis=-1)


def kinetic_energy(bodies: Bodies, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """[..., K] kinetic energy of each body (J)."""
    return kinetic_energies(bodies.masses, bodies.com, bodies.inertia, qpos, qvel)


def allowed_fraction(
    bodies: Bodies,
    qpos1: np.ndarray,
    qvel1: np.ndarray,
    change: np.ndarray,
    energy_limit: np.ndarray,
    contact_margin: float,
) -> np.ndarray:
    """[..., K] the largest fraction in [0, 1] of each body's velocity change `change` (qvel layout) that drives no
    vertex within contact_margin of the floor down faster than MuJoCo did and leaves kinetic energy <= energy_limit."""
    fraction = np.ones(qpos1.shape[:-1])
    for k, vertices in enumerate(bodies.vertices):
        placed = world_vertices(qpos1[..., k, :], vertices)
        offset = placed - qpos1[..., k, None, :3]
        near = placed[..., 2] - bodies.floor_z < contact_margin
        velocities = np.stack(np.broadcast_arrays(qvel1[..., k, :], change[..., k, :]), axis=-2)
        vertical = vertical_velocities(qpos1[..., k, :], velocities, offset)
        rising, pushed = vertical[..., 0, :], vertical[..., 1, :]
        # rising + f * pushed >= min(rising, 0): at rest or sinking, no push down; rising, at most to a stop.
        with np.errstate(divide="ignore", invalid="ignore"):
            limit = np.where(near & (pushed < 0), (np.minimum(rising, 0.0) - rising) / pushed, 1.0)
        fraction[..., k] = np.clip(limit.min(axis=-1), 0.0, 1.0)
    # Kinetic energy along the change is a quadratic a f^2 + b f + c; keep f where it stays <= energy_limit.
    c = kinetic_energy(bodies, qpos1, qvel1)
    a = kinetic_energy(bodies, qpos1, change)
    b = kinetic_energy(bodies, qpos1, qvel1 + change) - a - c
    slack = np.maximum(energy_limit - c, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.where(a > 0, (-b + np.sqrt(np.maximum(b * b + 4 * a * slack, 0.0))) / (2 * a), 1.0)
    return np.minimum(fraction, np.clip(root, 0.0, 1.0))


def projected_change(
    bodies: Bodies,
    qpos0: np.ndarray,
    qvel0: np.ndarray,
    qpos1: np.ndarray,
    qvel1: np.ndarray,
    correction: np.ndarray,
    contact_margin: float,
) -> tuple[np.ndarray, np.ndarray]:
    """A body-frame correction [..., K, 6] as a change of MuJoCo's post-step qvel, and the fraction of it allowed
    [..., K] (`allowed_fraction`; the energy limit is the larger kinetic energy, before or after the step)."""
    change = np.concatenate([rotations.rotate(qpos1[..., 3:], correction[..., :3]), correction[..., 3:]], axis=-1)
    limit = np.maximum(kinetic_energy(bodies, qpos0, qvel0), kinetic_energy(bodies, qpos1, qvel1))
    return change, allowed_fraction(bodies, qpos1, qvel1, change, limit, contact_margin)


def integrate(
    bodies: Bodies, qpos1: np.ndarray, qvel1: np.ndarray, change: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's post-step state with a velocity change (qvel layout) applied and integrated over the frame."""
    qvel = qvel1 + change
    qpos = np.empty_like(qpos1)
    qpos[..., :3] = qpos1[..., :3] + bodies.dt * change[..., :3]
    qpos[..., 3:] = rotations.normalize(
        rotations.multiply(qpos1[..., 3:], rotations.from_rotation_vector(bodies.dt * change[..., 3:]))
    )
    return qpos, qvel


def corrected(
    bodies: Bodies,
    qpos0: np.ndarray,
    qvel0: np.ndarray,
    qpos1: np.ndarray,
    qvel1: np.ndarray,
    correction: np.ndarray,
    contact_margin: float,
) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's post-step state with the projected correction applied and integrated over the frame."""
    change, fraction = projected_change(bodies, qpos0, qvel0, qpos1, qvel1, correction, contact_margin)
    return integrate(bodies, qpos1, qvel1, change * fraction[..., None])
