"""Newton–Euler quantities of one rigid body above a flat floor, and the semi-implicit Euler step of the recordings.

Conventions (those of the recordings and of Bullet/MuJoCo): the state at frame t holds the velocity that carried the
body from frame t-1 to frame t, so x_t = x_{t-1} + dt v_t and q_t = exp(w_t dt) q_{t-1} with w in the world frame.
Internally positions and linear velocities are those of the centre of mass (CoM), which is what Newton's law moves;
`poses_from_states` converts back to the mesh-frame origin the recordings store. The floor is the plane
z = floor_z with normal +z. An impulse is a 6-vector [linear (N s), angular about the CoM (N m s)], world frame.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from contactbench import rotations
from contactbench.errors import NotApplicable
from contactbench.kinematics import estimate_velocities
from contactbench.scene import Scene


class SingleBodyError(NotApplicable):
    """The hybrid model was handed a dataset with more than one body."""


@dataclass(frozen=True)
class RigidBody:
    mass: float  # kg
    inertia: np.ndarray  # [3, 3] kg m^2 about the CoM, mesh-frame axes
    com: np.ndarray  # [3] CoM in the mesh frame
    vertices: np.ndarray  # [V, 3] contact vertices relative to the CoM, mesh-frame axes
    width: float  # m, largest extent of the mesh's bounding box

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)


@dataclass(frozen=True)
class SingleBodyScene:
    """One rigid body with gravity, dt and floor, as the hybrid integrator and LCP need them."""

    body: RigidBody
    gravity: np.ndarray  # [3] m/s^2, world frame
    dt: float  # s between frames
    floor_z: float  # m


def single_body_scene(dataset: Scene) -> SingleBodyScene:
    """The single body of a scene with its mass properties, and the scene's gravity, dt and floor: what the hybrid's
    integrator and LCP work with."""
    if dataset.n_bodies != 1:
        raise SingleBodyError(
            f"the hybrid model supports single-body datasets; {dataset.name} has {dataset.n_bodies} bodies"
        )
    if dataset.static:
        raise NotApplicable(f"the hybrid model's LCP knows the flat floor only; {dataset.name} has terrain")
    mesh = dataset.body_mesh(0)
    com, inertia = dataset.inertial(0)
    body = RigidBody(
        mass=dataset.bodies[0].mass,
        inertia=np.asarray(inertia, dtype=np.float64),
        com=np.asarray(com, dtype=np.float64),
        vertices=mesh.vertices - com,
        width=mesh.width,
    )
    return SingleBodyScene(body=body, gravity=dataset.gravity, dt=dataset.dt, floor_z=dataset.floor_z)


@dataclass(frozen=True)
class State:
    """Rigid-body states with any leading batch shape; all vectors in the world frame."""

    position: np.ndarray  # [..., 3] CoM
    orientation: np.ndarray  # [..., 4] w, x, y, z
    linear: np.ndarray  # [..., 3] CoM velocity
    angular: np.ndarray  # [..., 3] angular velocity

    def __getitem__(self, index) -> State:
        return State(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


def states_from_poses(poses: np.ndarray, body: RigidBody, dt: float) -> State:
    """States at every frame of poses [..., T, 7] (mesh-frame origins), velocities by backward differences.

    Frame 0 has no predecessor and reuses frame 1's velocity, as `estimate_velocities` does.
    """
    orientation = rotations.normalize(poses[..., 3:])
    position = poses[..., :3] + rotations.rotate(orientation, body.com)
    com_poses = np.concatenate([position, orientation], axis=-1)
    velocities = estimate_velocities(com_poses[..., None, :], dt)[..., 0, :]
    return State(position, orientation, velocities[..., :3], velocities[..., 3:])


def poses_from_states(state: State, body: RigidBody) -> np.ndarray:
    """Mesh-frame origin poses [..., 7] of the states."""
    origin = state.position - rotations.rotate(state.orientation, body.com)
    return np.concatenate([origin, state.orientation], axis=-1)


def world_inverse_inertia(orientation: np.ndarray, body: RigidBody) -> np.ndarray:
    """R I^-1 R^T [..., 3, 3]."""
    rotation = rotations.to_matrix(orientation)
    return rotation @ np.linalg.inv(body.inertia) @ np.swapaxes(rotation, -1, -2)


def world_inertia(orientation: np.ndarray, body: RigidBody) -> np.ndarray:
    """R I R^T [..., 3, 3]."""
    rotation = rotations.to_matrix(orientation)
    return rotation @ body.inertia @ np.swapaxes(rotation, -1, -2)


def unconstrained_velocities(state: State, scene: SingleBodyScene) -> tuple[np.ndarray, np.ndarray]:
    """Velocities after one step of gravity and the (explicit) gyroscopic term, before any contact impulse."""
    inertia = world_inertia(state.orientation, scene.body)
    momentum = np.einsum("...ij,...j->...i", inertia, state.angular)
    gyroscopic = np.einsum(
        "...ij,...j->...i", world_inverse_inertia(state.orientation, scene.body), np.cross(state.angular, momentum)
    )
    return state.linear + scene.dt * scene.gravity, state.angular - scene.dt * gyroscopic


def velocity_change(orientation: np.ndarray, impulse: np.ndarray, body: RigidBody) -> tuple[np.ndarray, np.ndarray]:
    """Linear and angular velocity change M^-1 impulse for impulses [..., 6] (world frame, torque about the CoM)."""
    angular = np.einsum("...ij,...j->...i", world_inverse_inertia(orientation, body), impulse[..., 3:])
    return impulse[..., :3] / body.mass, angular


def impulse_between(
    state: State, next_linear: np.ndarray, next_angular: np.ndarray, scene: SingleBodyScene
) -> np.ndarray:
    """The contact impulse [..., 6] that turns `state`'s velocities into the next ones: M (v' - v_unconstrained)."""
    linear, angular = unconstrained_velocities(state, scene)
    inertia = world_inertia(state.orientation, scene.body)
    angular_impulse = np.einsum("...ij,...j->...i", inertia, next_angular - angular)
    return np.concatenate([scene.body.mass * (next_linear - linear), angular_impulse], axis=-1)


def integrate(state: State, linear: np.ndarray, angular: np.ndarray, dt: float) -> State:
    """Next state from the new velocities: x' = x + dt v', q' = exp(w' dt) q."""
    turn = rotations.from_rotation_vector(angular * dt)
    orientation = rotations.normalize(rotations.multiply(turn, state.orientation))
    return State(state.position + dt * linear, orientation, linear, angular)


def vertex_offsets(orientation: np.ndarray, body: RigidBody) -> np.ndarray:
    """World-frame vectors [..., V, 3] from the CoM to each contact vertex."""
    return rotations.rotate(orientation[..., None, :], body.vertices)


def vertex_gaps(state: State, scene: SingleBodyScene) -> np.ndarray:
    """Signed height of each vertex above the floor [..., V] (negative: penetrating)."""
    return state.position[..., None, 2] + vertex_offsets(state.orientation, scene.body)[..., 2] - scene.floor_z


def normal_velocities(offsets: np.ndarray, linear: np.ndarray, angular: np.ndarray) -> np.ndarray:
    """Velocity of each vertex along the floor normal [..., V]: (v + w x r)_z."""
    return linear[..., None, 2] + np.cross(angular[..., None, :], offsets)[..., 2]


def normal_torque_arms(offsets: np.ndarray) -> np.ndarray:
    """r x n for n = +z [..., V, 3]: the torque a unit normal impulse at each vertex exerts about the CoM."""
    return np.stack([offsets[..., 1], -offsets[..., 0], np.zeros_like(offsets[..., 0])], axis=-1)


def normal_wrench(offsets: np.ndarray, normal_impulses: np.ndarray) -> np.ndarray:
    """Body impulse [..., 6] of normal impulses [..., V] (N s, along +z) at the vertices."""
    torque = np.einsum("...v,...vi->...i", normal_impulses, normal_torque_arms(offsets))
    force = np.zeros_like(torque)
    force[..., 2] = normal_impulses.sum(axis=-1)
    return np.concatenate([force, torque], axis=-1)


def delassus(orientation: np.ndarray, offsets: np.ndarray, body: RigidBody) -> np.ndarray:
    """Normal-velocity response [..., V, V] of vertex i to a unit normal impulse at vertex j: 1/m + (r_i x n)^T I^-1
    (r_j x n)."""
    arms = normal_torque_arms(offsets)
    inverse_inertia = world_inverse_inertia(orientation, body)
    return 1.0 / body.mass + np.einsum("...vi,...ij,...wj->...vw", arms, inverse_inertia, arms)
