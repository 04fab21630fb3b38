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


def world_vertices(poses: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Mesh vertices [V, 3] placed at poses [..., 7]: returns [..., V, 3]."""
    q = poses[..., None, 3:]
    return poses[..., None, :3] + rotations.rotate(q, vertices)
