"""Quaternion and rotation helpers; quaternions are (w, x, y, z) everywhere in the package."""

from __future__ import annotations

import numpy as np


def normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions. A zero quaternion, which is how zero-filled frames past a toss's end arrive (no orientation
    recorded), becomes NaN without a warning: those frames are masked out wherever they are read."""
    with np.errstate(invalid="ignore"):  # 0/0 only: a non-zero quaternion never divides by a zero norm
        return q / np.linalg.norm(q, axis=-1, keepdims=True)


def conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(normalize(q), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def from_matrix(m: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] to unit quaternions with w >= 0 (Shepperd's method)."""
    m = np.asarray(m, dtype=float)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    candidates = np.stack(
        [
            np.stack(
                [1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
            ),
            np.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + 2 * m[..., 0, 0] - trace,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 + 2 * m[..., 1, 1] - trace,
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 + 2 * m[..., 2, 2] - trace,
                ],
                -1,
            ),
        ],
        axis=-2,
    )
    # Pick the numerically largest of the four equivalent expressions (the diagonal entry of each row).
    pivot = np.argmax(
        np.stack(
            [1 + trace, 1 + 2 * m[..., 0, 0] - trace, 1 + 2 * m[..., 1, 1] - trace, 1 + 2 * m[..., 2, 2] - trace], -1
        ),
        axis=-1,
    )
    q = np.take_along_axis(candidates, pivot[..., None, None], axis=-2)[..., 0, :]
    q = normalize(q)
    return np.where(q[..., :1] < 0, -q, q)


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v [..., 3] by unit quaternions q [..., 4] (broadcasting).

    Written component by component: np.cross's temporaries made this several times slower on the millions of frames
    a batched rollout returns.
    """
    w, x, y, z = (q[..., i] for i in range(4))
    vx, vy, vz = (v[..., i] for i in range(3))
    tx, ty, tz = 2 * (y * vz - z * vy), 2 * (z * vx - x * vz), 2 * (x * vy - y * vx)
    rotated = np.empty(np.broadcast_shapes(q.shape[:-1], v.shape[:-1]) + (3,), dtype=np.result_type(q, v, float))
    rotated[..., 0] = vx + w * tx + (y * tz - z * ty)
    rotated[..., 1] = vy + w * ty + (z * tx - x * tz)
    rotated[..., 2] = vz + w * tz + (x * ty - y * tx)
    return rotated


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle in [0, pi] taking orientation a to b; q and -q are the same orientation."""
    relative = multiply(conjugate(a), b)
    vector_norm = np.linalg.norm(relative[..., 1:], axis=-1)
    return 2.0 * np.arctan2(vector_norm, np.abs(relative[..., 0]))


def from_axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    axis = np.asarray(axis, dtype=float)
    angle = np.asarray(angle, dtype=float)[..., None]
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return np.concatenate([np.cos(angle / 2), np.sin(angle / 2) * axis], axis=-1)


def tilt(about_x: float, about_y: float) -> np.ndarray:
    """The rotation about world x by about_x, then about world y by about_y (a tilted floor's orientation)."""
    return multiply(from_axis_angle([0.0, 1.0, 0.0], about_y), from_axis_angle([1.0, 0.0, 0.0], about_x))


def from_rotation_vector(rotvec: np.ndarray) -> np.ndarray:
    rotvec = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = angle / 2
    # sin(x/2)/x -> 1/2 as x -> 0
    scale = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0), 0.5)
    return np.concatenate([np.cos(half), scale * rotvec], axis=-1)


def to_rotation_vector(q: np.ndarray) -> np.ndarray:
    q = normalize(q)
    q = np.where(q[..., :1] < 0, -q, q)
    vector_norm = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(vector_norm, q[..., :1])
    scale = np.where(vector_norm > 1e-12, angle / np.where(vector_norm > 1e-12, vector_norm, 1.0), 2.0)
    return scale * q[..., 1:]


def uniform_random(rng: np.random.Generator, count: int) -> np.ndarray:
    """Orientations drawn uniformly on SO(3) (normalised 4-D Gaussians), w >= 0."""
    q = normalize(rng.standard_normal((count, 4)))
    return np.where(q[..., :1] < 0, -q, q)


def angular_velocity_from_quaternions(q0: np.ndarray, q1: np.ndarray, dt: float) -> np.ndarray:
    """World-frame angular velocity that turns q0 into q1 in dt at constant rate."""
    delta = multiply(q1, conjugate(q0))
    return to_rotation_vector(delta) / dt


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    return np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)
