"""Rigid-body kinematics from recorded poses: velocities by finite differences, world vertex positions."""

from __future__ import annotations

import numpy as np

from contactbench import rotations


def estimate_velocities(poses: np.ndarray, dt: float) -> np.ndarray:
    """World-frame [v, w] per frame from poses [..., T, K, 7] by backward differences.

    A backward difference is exactly the velocity a semi-implicit Euler engine (Bullet, MuJoCo) stores
    after a step, since x_t = x_{t-1} + dt v_t there. Frame 0 reuses frame 1's estimate.
    """
    linear = np.diff(poses[..., :3], axis=-3) / dt
    angular = rotations.angular_velocity_from_quaternions(poses[..., :-1, :, 3:], poses[..., 1:, :, 3:], dt)
    velocities = np.concatenate([linear, angular], axis=-1)
    return np.concatenate([velocities[..., :1, :, :], velocities], axis=-3)


def fit_velocities(poses: np.ndarray, dt: float) -> np.ndarray:
    """World-frame [v, w] at every frame of short windows poses [..., C, K, 7] by least squares over the whole window:
    each position coordinate a quadratic in time, the rotation (relative to the window's middle frame) a rotation
    vector linear in time. Velocities follow the semi-implicit convention x_t - x_{t-1} = dt v_t, taken on the fit.

    Where a backward difference reads one frame's noise twice (sigma sqrt(2) / dt), the fit averages it over the
    window: exact on free flight and at rest (quadratic positions, constant spin), robust to tracker noise. Windows of
    fewer than three frames fall back to backward differences."""
    frames = poses.shape[-3]
    if frames < 3:
        return estimate_velocities(poses, dt)
    time = (np.arange(frames) - (frames - 1) / 2) * dt
    # Positions: x(t) = a + b t + c t^2, fitted per coordinate; v_t = (x(t) - x(t - dt)) / dt on the fit.
    design = np.stack([np.ones(frames), time, time**2], axis=-1)  # [C, 3]
    solve = np.linalg.pinv(design)  # [3, C]
    coefficients = np.einsum("pc,...ckd->...pkd", solve, poses[..., :3])  # [..., 3, K, 3]
    b, c = coefficients[..., 1, :, :], coefficients[..., 2, :, :]
    linear = b[..., None, :, :] + c[..., None, :, :] * (2 * time[:, None, None] - dt)
    # Orientation: r(t) = log(q_mid^-1 q(t)) (body frame of the middle frame) ~ r0 + w_body t.
    middle = poses[..., (frames - 1) // 2 : (frames - 1) // 2 + 1, :, 3:]
    relative = rotations.to_rotation_vector(rotations.multiply(rotations.conjugate(middle), poses[..., 3:]))
    slope = np.einsum("c,...ckd->...kd", (time - time.mean()) / np.sum((time - time.mean()) ** 2), relative)
    angular = rotations.rotate(middle[..., 0, :, :], slope)  # world frame
    return np.concatenate([linear, np.broadcast_to(angular[..., None, :, :], linear.shape)], axis=-1)


def world_vertices(poses: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Mesh vertices [V, 3] placed at poses [..., 7]: returns [..., V, 3]."""
    q = poses[..., None, 3:]
    return poses[..., None, :3] + rotations.rotate(q, vertices)


def hinge_anchor(parent: np.ndarray, joint) -> np.ndarray:
    """The hinge's anchor in the world [..., 3] for parent poses [..., 7] (a recordings.Joint)."""
    return world_vertices(parent, joint.parent_anchor[None])[..., 0, :]


def hinge_child(
    parent: np.ndarray, parent_velocity: np.ndarray, joint, angle: np.ndarray, rate: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The child's pose [..., 7] and world velocity [..., 6] from its parent's pose [..., 7] and world velocity
    [..., 6], the joint angle [...] (rad) and its rate [...] (rad/s); the child's frame is the parent's turned by the
    angle about the axis, its anchor on the parent's."""
    turn = rotations.from_axis_angle(joint.axis, angle)
    orientation = rotations.multiply(parent[..., 3:], turn)
    anchor = hinge_anchor(parent, joint)
    position = anchor - rotations.rotate(orientation, np.broadcast_to(joint.child_anchor, anchor.shape))
    axis = rotations.rotate(parent[..., 3:], np.broadcast_to(joint.axis, anchor.shape))
    spin = parent_velocity[..., 3:]
    angular = spin + np.asarray(rate)[..., None] * axis
    linear = parent_velocity[..., :3] + np.cross(spin, anchor - parent[..., :3]) + np.cross(angular, position - anchor)
    return np.concatenate([position, orientation], axis=-1), np.concatenate([linear, angular], axis=-1)


def hinge_coordinates(
    parent: np.ndarray, parent_velocity: np.ndarray, child: np.ndarray, child_velocity: np.ndarray, joint
) -> tuple[np.ndarray, np.ndarray]:
    """The joint angle [...] (rad, in (-pi, pi]) and rate [...] (rad/s) of a child pose [..., 7] and world velocity
    [..., 6] relative to its parent's: the turn about the axis that best explains the relative orientation."""
    relative = rotations.multiply(rotations.conjugate(parent[..., 3:]), child[..., 3:])
    angle = 2 * np.arctan2(relative[..., 1:] @ joint.axis, relative[..., 0])
    angle = (angle + np.pi) % (2 * np.pi) - np.pi
    axis = rotations.rotate(parent[..., 3:], np.broadcast_to(joint.axis, parent.shape[:-1] + (3,)))
    rate = np.einsum("...i,...i->...", child_velocity[..., 3:] - parent_velocity[..., 3:], axis)
    return angle, rate


def hinge_errors(poses: np.ndarray, joints) -> tuple[np.ndarray, np.ndarray]:
    """How far poses [..., K, 7] (unit quaternions) break each hinge: the distance between its two anchors (m) and the
    angle between its two axes (rad), each [..., J]."""
    gaps, angles = [], []
    for joint in joints:
        parent, child = poses[..., joint.parent, :], poses[..., joint.child, :]
        anchors = [
            world_vertices(pose, anchor[None])[..., 0, :]
            for pose, anchor in ((parent, joint.parent_anchor), (child, joint.child_anchor))
        ]
        gaps.append(np.linalg.norm(anchors[0] - anchors[1], axis=-1))
        axis_parent = rotations.rotate(parent[..., 3:], joint.axis)
        axis_child = rotations.rotate(child[..., 3:], joint.axis)
        cross = np.linalg.norm(np.cross(axis_parent, axis_child), axis=-1)
        angles.append(np.arctan2(cross, np.einsum("...i,...i->...", axis_parent, axis_child)))
    shape = poses.shape[:-2] + (0,)
    return (np.stack(gaps, axis=-1), np.stack(angles, axis=-1)) if joints else (np.zeros(shape), np.zeros(shape))
