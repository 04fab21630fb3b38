"""Shape matching (Müller et al. 2005): the rigid motion of a rest mesh that best fits predicted vertices.

For rest vertices p_i (centroid p̄) and predicted vertices x_i (centroid x̄), the rotation minimising
Σ_i |R (p_i − p̄) − (x_i − x̄)|² is the rotational factor of the polar decomposition of
A = Σ_i (x_i − x̄)(p_i − p̄)ᵀ; with A = U S Vᵀ it is U diag(1, 1, det(U Vᵀ)) Vᵀ (the sign keeps it a rotation,
not a reflection). The mesh frame's origin then sits at x̄ − R p̄. All vertices weigh the same; everything is
batched over leading axes.
"""

from __future__ import annotations

import numpy as np
import torch

from contactbench import rotations


def fit_rigid_transform(rest_vertices: torch.Tensor, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation [..., 3, 3] and translation [..., 3] with vertices ≈ rest_vertices @ Rᵀ + t, least squares.

    rest_vertices [V, 3] (mesh frame), vertices [..., V, 3] (world).
    """
    rest_centroid = rest_vertices.mean(dim=-2)
    centroid = vertices.mean(dim=-2)
    covariance = (vertices - centroid[..., None, :]).transpose(-1, -2) @ (rest_vertices - rest_centroid)
    u, _, vh = torch.linalg.svd(covariance)
    reflection = torch.sign(torch.linalg.det(u @ vh))
    # A zero determinant only arises for degenerate (flat) vertex sets; keep those a proper rotation too.
    reflection = torch.where(reflection == 0, torch.ones_like(reflection), reflection)
    u = torch.cat([u[..., :2], u[..., 2:] * reflection[..., None, None]], dim=-1)
    rotation = u @ vh
    translation = centroid - (rotation @ rest_centroid[..., None])[..., 0]
    return rotation, translation


def project_to_rigid(rest_vertices: torch.Tensor, body_slices: list[slice], vertices: torch.Tensor) -> torch.Tensor:
    """Each body's vertices [..., n, 3] replaced by its rest mesh at the best-fitting rigid motion."""
    projected = []
    for nodes in body_slices:
        rotation, translation = fit_rigid_transform(rest_vertices[nodes], vertices[..., nodes, :])
        projected.append(rest_vertices[nodes] @ rotation.transpose(-1, -2) + translation[..., None, :])
    return torch.cat(projected, dim=-2)


def poses_from_vertices(rest_vertices: np.ndarray, body_slices: list[slice], vertices: np.ndarray) -> np.ndarray:
    """Body poses [..., K, 7] (position, unit quaternion w-first) best fitting node positions [..., n, 3]."""
    rest = torch.as_tensor(rest_vertices, dtype=torch.float64)
    points = torch.as_tensor(vertices, dtype=torch.float64)
    poses = []
    for nodes in body_slices:
        rotation, translation = fit_rigid_transform(rest[nodes], points[..., nodes, :])
        poses.append(np.concatenate([translation.numpy(), rotations.from_matrix(rotation.numpy())], axis=-1))
    return np.stack(poses, axis=-2)
