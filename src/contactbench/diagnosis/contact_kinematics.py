"""What the contact signatures read off recorded poses, per body and frame: the contact geometry at frame t and the
floor's force and torque in the step into it (diagnosis.contact_signatures).

A step is the motion from frame t-1 to frame t: its acceleration (v_t - v_{t-1}) / dt is what the engine's forces did
in it (exact for the recorded post-step velocities of a semi-implicit engine); the floor's whole push on a free body is
then m (a + g), its normal part the load N, and its torque about the centre of mass follows from Euler's equations.

Bodies on joints: the hinge force acts between them, so one body's motion does not give the floor's force on it. The
tree's total momentum does, since the joint's forces cancel in it: while exactly one body of a tree touches the floor
(and the others are clear of it), the floor's whole force on the tree, sum_k m_k a_k + M g, and its torque about the
tree's centre of mass, sum_k [I_k alpha_k + w_k x I_k w_k + (c_k - C) x m_k a_k] (gravity has none about it), act at
that body's contact. Such a body's quantities are then the tree's force and torque per unit tree mass, with its own
contact geometry and vertex velocities, its arms taken from the tree's centre of mass. While several bodies of a tree
touch, how the load splits between them is not in the poses: no body of the tree is read in contact then.
"""

from __future__ import annotations

import numpy as np

from contactbench import rotations
from contactbench.diagnosis.free_flight import systems
from contactbench.diagnosis.phases import CONTACT_HEIGHT, recorded_velocities
from contactbench.scene import Recordings, Split

# Vertices within this fraction of the body width above the lowest one carry the contact (engines sink 5-10 mm and
# rock, so a resting face's vertices lie up to a few mm apart).
TOUCH = 0.02
# Flat on a face: the most downward face normal within this angle of -z, and the body tilting slower than
# TILT_SPEED at its edges (|w_horizontal| width / 2). Looser selections let tumbling in, and a null cube then reads
# as anisotropic at the margin with a far worse fit (docs/results/calibration.md).
FLAT_ANGLE = np.radians(6.0)


def _isolated(dataset: Recordings, body: int, poses: np.ndarray, tree: tuple[int, ...] = ()) -> np.ndarray:
    """[N, T] True where no other body's bounding sphere (outside the body's own tree) comes within the contact height
    of this one's."""
    radii = [float(np.linalg.norm(dataset.body_mesh(k).vertices, axis=1).max()) for k in range(dataset.n_bodies)]
    clear = np.ones(poses.shape[:2], dtype=bool)
    for other in range(dataset.n_bodies):
        if other != body and other not in tree:
            gap = np.linalg.norm(poses[:, :, body, :3] - poses[:, :, other, :3], axis=-1)
            clear &= gap - radii[body] - radii[other] > CONTACT_HEIGHT * dataset.widths()[body]
    return clear


def _state(dataset: Recordings, split: Split, body: int) -> dict:
    """One body's own motion and contact geometry [N, T, ...], and the force and torque (about its centre of mass)
    that act on it in the step into frame t."""
    poses = np.nan_to_num(split.poses)[:, :, body]
    velocities = np.nan_to_num(recorded_velocities(split, dataset.dt)[:, :, body])
    mesh = dataset.body_mesh(body)
    width = float(dataset.widths()[body])
    com, inertia = dataset.inertial(body)
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
    # the torque about the centre of mass that acted in the step (Euler's equations, world frame)
    torque = np.einsum("ntij,ntj->nti", world_inertia, angular_acceleration) + np.cross(
        omega, np.einsum("ntij,ntj->nti", world_inertia, omega)
    )
    return {
        "width": width,
        "mass": dataset.bodies[body].mass,
        "centre": centre,
        "vertices": vertices,
        "heights": heights,
        "lowest": lowest,
        "omega": omega,
        "arms": arms,
        "vertex_velocity": vertex_velocity,
        "flatness": flatness,
        "acceleration": acceleration,
        "torque": torque,
        "finite": np.isfinite(split.poses[:, :, body]).all(axis=-1),
    }


def _kinematics(state: dict, g: float, valid: np.ndarray, in_contact: np.ndarray, flying: np.ndarray) -> dict:
    """The per-frame quantities the rows read, from a body's state whose force and torque are the floor's."""
    width, lowest = state["width"], state["lowest"]
    omega = state["omega"]
    push = state["acceleration"] + np.array([0.0, 0.0, g])  # the floor's force per unit mass
    return {
        "width": np.array(width),
        "g": np.array(g),
        "valid": valid,
        "in_contact": in_contact,
        "flying": flying,
        "centre": state["centre"],
        "touching": state["heights"] < lowest[..., None] + TOUCH * width,
        "flat": state["flatness"] > np.cos(FLAT_ANGLE),
        "tilt_speed": np.linalg.norm(omega[..., :2], axis=-1) * width / 2,
        "arms": state["arms"],
        "vertex_velocity": state["vertex_velocity"],
        "omega": omega,
        "push": push,
        "load": push[..., 2],
        "torque_per_mass": state["torque"] / state["mass"],
    }


def body_kinematics(dataset: Recordings, split: Split, body: int) -> dict[str, np.ndarray]:
    """A free body's per-frame quantities [N, T, ...]: the contact geometry at frame t and the step into it."""
    state = _state(dataset, split, body)
    valid = split.valid_mask() & state["finite"]
    valid &= _isolated(dataset, body, np.nan_to_num(split.poses))
    in_contact = valid & (state["lowest"] < CONTACT_HEIGHT * state["width"])
    return _kinematics(state, float(np.linalg.norm(dataset.gravity)), valid, in_contact, valid & ~in_contact)


def tree_kinematics(dataset: Recordings, split: Split, tree: tuple[int, ...]) -> dict[int, dict[str, np.ndarray]]:
    """Per body of a tree of jointed bodies, its per-frame quantities as body_kinematics gives a free body's, with the
    floor's force and torque read off the whole tree (module docstring): in contact only where it is the tree's one
    body touching the floor, flying where none of them touches."""
    states = {k: _state(dataset, split, k) for k in tree}
    poses = np.nan_to_num(split.poses)
    valid = split.valid_mask()
    for k in tree:
        valid = valid & states[k]["finite"] & _isolated(dataset, k, poses, tree)
    touches = {k: states[k]["lowest"] < CONTACT_HEIGHT * states[k]["width"] for k in tree}
    total = sum(states[k]["mass"] for k in tree)
    centre = sum(states[k]["mass"] * states[k]["centre"] for k in tree) / total
    acceleration = sum(states[k]["mass"] * states[k]["acceleration"] for k in tree) / total
    torque = sum(
        states[k]["torque"] + np.cross(states[k]["centre"] - centre, states[k]["mass"] * states[k]["acceleration"])
        for k in tree
    )
    flying = valid & ~np.any([touches[k] for k in tree], axis=0)
    g = float(np.linalg.norm(dataset.gravity))
    out = {}
    for k in tree:
        alone = touches[k] & ~np.any([touches[j] for j in tree if j != k], axis=0)
        as_tree = {
            **states[k],
            "mass": total,
            "acceleration": acceleration,
            "torque": torque,
            "arms": states[k]["vertices"] - centre[..., None, :],
        }
        out[k] = _kinematics(as_tree, g, valid, valid & alone, flying)
    return out


def split_kinematics(dataset: Recordings, split: Split) -> list[dict[str, np.ndarray]]:
    """Every body's per-frame quantities, in body order: a free body's own, a tree's bodies' read off the tree."""
    found: dict[int, dict] = {}
    for tree in systems(dataset):
        if len(tree) == 1:
            found[tree[0]] = body_kinematics(dataset, split, tree[0])
        else:
            found.update(tree_kinematics(dataset, split, tree))
    return [found[k] for k in range(dataset.n_bodies)]
