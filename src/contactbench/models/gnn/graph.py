"""Graphs of rigid-body scenes: mesh vertices as nodes, mesh edges both ways, collision edges between bodies.

Every body's mesh vertices are nodes, body after body. Edges are directed (sender, receiver) pairs:
- mesh edges: each undirected edge of each body's triangle mesh, in both directions; fixed for a scene;
- collision edges: every pair of vertices of *different* bodies closer than the collision radius, both directions;
  rebuilt from the current positions at every step.
The floor is not a node: it enters the node features (see simulator.py), so single-body scenes have mesh edges only.

Collision radius: a fraction of the widest body's width (`collision_radius`), default 0.8. A corner touching a
cube anywhere on a face is at most √2/2 ≈ 0.71 widths from that face's nearest corner, so 0.8 links every
corner-face contact between equal cubes, while bodies more than 0.8 widths apart exchange no messages. Edge-edge and
face-face contacts are linked only when some corners come that close; this blind spot of vertex-only graphs is what
Allen et al. (2022) add face-face edges for. The same radius clips the floor distance feature and scales
displacements (simulator.py).
Collision edges come from a dense [B, n, n] distance test: scenes have at most a few hundred vertices, for which
this costs little next to the network and needs no neighbour-search package (torch-cluster is not installed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from contactbench.kinematics import world_vertices
from contactbench.scene import Scene

DEFAULT_COLLISION_RADIUS_FRACTION = 0.8


@dataclass(frozen=True)
class MeshScene:
    """The bodies of a dataset laid out as graph nodes."""

    rest_vertices: np.ndarray  # [n, 3] each body's mesh vertices in its own mesh frame, body after body
    body_starts: np.ndarray  # [K + 1] body k owns nodes body_starts[k] : body_starts[k + 1]
    mesh_edges: np.ndarray  # [2, E] directed (sender, receiver) node pairs, both directions of every mesh edge
    widths: np.ndarray  # [K] body widths (largest bounding-box extent), m
    faces: np.ndarray  # [F, 3] node indices of every body's triangles, counter-clockwise seen from outside

    @classmethod
    def of(cls, dataset: Scene) -> MeshScene:
        meshes = [dataset.body_mesh(k) for k in range(dataset.n_bodies)]
        body_starts = np.cumsum([0] + [len(mesh.vertices) for mesh in meshes])
        undirected = np.concatenate([mesh.edges + start for mesh, start in zip(meshes, body_starts)])
        mesh_edges = np.concatenate([undirected.T, undirected.T[::-1]], axis=1)
        return cls(
            rest_vertices=np.concatenate([mesh.vertices for mesh in meshes]),
            body_starts=body_starts,
            mesh_edges=mesh_edges,
            widths=np.array([mesh.width for mesh in meshes]),
            faces=np.concatenate([mesh.faces + start for mesh, start in zip(meshes, body_starts)]),
        )

    @property
    def n_nodes(self) -> int:
        return len(self.rest_vertices)

    @property
    def n_bodies(self) -> int:
        return len(self.widths)

    @property
    def node_body(self) -> np.ndarray:
        """[n] the body each node belongs to."""
        return np.repeat(np.arange(self.n_bodies), np.diff(self.body_starts))

    def body_slices(self) -> list[slice]:
        return [slice(int(start), int(stop)) for start, stop in zip(self.body_starts[:-1], self.body_starts[1:])]

    def world_vertices(self, poses: np.ndarray) -> np.ndarray:
        """Node positions [..., n, 3] of bodies at poses [..., K, 7]."""
        return np.concatenate(
            [world_vertices(poses[..., k, :], self.rest_vertices[nodes]) for k, nodes in enumerate(self.body_slices())],
            axis=-2,
        )


def collision_radius(widths: np.ndarray, fraction: float = DEFAULT_COLLISION_RADIUS_FRACTION) -> float:
    """Collision radius (m): `fraction` of the widest body's width."""
    return float(fraction * np.max(widths))


def batched_mesh_edges(mesh_edges: torch.Tensor, n_nodes: int, batch_size: int) -> torch.Tensor:
    """The scene's mesh edges [2, E] repeated for B graphs of n nodes stacked in one: [2, B * E], graph-major."""
    offsets = torch.arange(batch_size, device=mesh_edges.device) * n_nodes
    return (mesh_edges[:, None, :] + offsets[None, :, None]).reshape(2, -1)


def collision_edges(positions: torch.Tensor, node_body: torch.Tensor, radius: float) -> torch.Tensor:
    """Directed edges [2, Ec] between nodes of different bodies closer than `radius`, in B graphs stacked in one.

    positions [B, n, 3]; node_body [n]. Node i of graph b is node b * n + i of the stacked graph.
    """
    batch_size, n_nodes, _ = positions.shape
    other_body = node_body[:, None] != node_body[None, :]
    if not bool(other_body.any()):
        return torch.zeros((2, 0), dtype=torch.long, device=positions.device)
    distances = torch.linalg.vector_norm(positions[:, :, None, :] - positions[:, None, :, :], dim=-1)
    graph, receivers, senders = torch.nonzero((distances < radius) & other_body, as_tuple=True)
    offsets = graph * n_nodes
    return torch.stack([senders + offsets, receivers + offsets])


def build_edges(
    positions: torch.Tensor, node_body: torch.Tensor, mesh_edges: torch.Tensor, radius: float
) -> tuple[torch.Tensor, int]:
    """Edge index [2, B * E + Ec] of B stacked graphs (mesh edges first, then collision edges) and B * E."""
    batch_size, n_nodes, _ = positions.shape
    mesh = batched_mesh_edges(mesh_edges, n_nodes, batch_size)
    return torch.cat([mesh, collision_edges(positions, node_body, radius)], dim=1), mesh.shape[1]
