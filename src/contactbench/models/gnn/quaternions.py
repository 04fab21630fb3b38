"""Differentiable w-first unit quaternions in torch (the numpy twins live in contactbench.rotations)."""

from __future__ import annotations

import math

import torch

# Below this rotation-vector length the closed forms switch to their series limits (exact to float64 rounding).
SMALL_ANGLE = 1e-9


def multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a ⊗ b of quaternions [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def conjugate(q: torch.Tensor) -> torch.Tensor:
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Vectors v [..., 3] rotated by unit quaternions q [..., 4] (broadcasting)."""
    q, v = torch.broadcast_tensors(q, torch.cat([torch.zeros_like(v[..., :1]), v], dim=-1))
    w, axis, v = q[..., :1], q[..., 1:], v[..., 1:]
    t = 2.0 * torch.linalg.cross(axis, v, dim=-1)
    return v + w * t + torch.linalg.cross(axis, t, dim=-1)


def from_rotation_vector(rotation_vector: torch.Tensor) -> torch.Tensor:
    """exp: the unit quaternion of a rotation vector [..., 3] (axis × angle)."""
    angle = torch.linalg.vector_norm(rotation_vector, dim=-1, keepdim=True)
    # sin(θ/2)/θ = sinc(θ/2π)/2 with torch's normalised sinc: smooth through θ = 0
    return torch.cat([torch.cos(angle / 2), 0.5 * torch.sinc(angle / (2 * math.pi)) * rotation_vector], dim=-1)


def to_rotation_vector(q: torch.Tensor) -> torch.Tensor:
    """log: the rotation vector [..., 3] of unit quaternions [..., 4], angle in [0, π]."""
    q = torch.where(q[..., :1] < 0, -q, q)
    vector_norm = torch.linalg.vector_norm(q[..., 1:], dim=-1, keepdim=True)
    small = vector_norm < SMALL_ANGLE
    safe_norm = torch.where(small, torch.ones_like(vector_norm), vector_norm)
    scale = torch.where(small, 2.0 / q[..., :1], 2.0 * torch.atan2(vector_norm, q[..., :1]) / safe_norm)
    return scale * q[..., 1:]


def angular_velocity(q0: torch.Tensor, q1: torch.Tensor, dt: float) -> torch.Tensor:
    """World-frame angular velocity [..., 3] that turns q0 into q1 in dt at a constant rate."""
    return to_rotation_vector(multiply(q1, conjugate(q0))) / dt
