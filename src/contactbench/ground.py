"""The ground a scene's bodies meet — the floor, static convex meshes, height fields — as signed distance and normal.

One definition serves the metrics (penetration against the true surface) and the learned models (node features):
- floor: z − floor_z, normal +z;
- a static convex mesh: max over its face planes of n·p − d (exact inside and wherever the nearest feature is a
  face; outside near an edge or corner it is a lower bound of the distance), normal of that plane;
- a height field: the height above its triangulated surface (cells split along the (i, j)-(i+1, j+1) diagonal,
  recordings.HeightField), times the triangle normal's vertical component (the distance to the triangle's plane);
  +inf beyond the grid, where the floor takes over.
The ground's distance is the smallest over its parts, with that part's normal. Works on torch tensors of any
leading shape (float64 or float32); `signed_distance` wraps it for numpy arrays.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from contactbench import rotations
from contactbench.meshes import Mesh
from contactbench.scene import HeightField, Scene, Static


def halfspaces(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """A convex mesh as its distinct face planes: unit outward normals [P, 3] and offsets [P] (inside: n·p ≤ d)."""
    v0, v1, v2 = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    normals = np.cross(v1 - v0, v2 - v0)
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 1e-12 * mesh.width**2
    normals = normals[keep] / lengths[keep, None]
    offsets = np.einsum("ij,ij->i", normals, v0[keep])
    planes = np.round(np.concatenate([normals, offsets[:, None] / mesh.width], axis=1), 9)
    _, first = np.unique(planes, axis=0, return_index=True)
    first = np.sort(first)
    return normals[first], offsets[first]


@dataclass(frozen=True)
class _Field:
    rotation: np.ndarray  # [3, 3] field frame -> world
    origin: np.ndarray  # [3]
    field: HeightField


@dataclass(frozen=True)
class Ground:
    """Everything static in a scene, in the world frame."""

    floor_z: float
    plane_normals: list[np.ndarray]  # per static mesh, [P, 3] world
    plane_offsets: list[np.ndarray]  # per static mesh, [P]
    fields: list[_Field]

    @classmethod
    def of(cls, scene: Scene) -> Ground:
        return cls.of_static(scene.floor_z, scene.static, scene.meshes)

    @classmethod
    def of_static(cls, floor_z: float, static: Sequence[Static], meshes: Mapping[str, Mesh]) -> Ground:
        normals, offsets, fields = [], [], []
        for entry in static:
            rotation = rotations.to_matrix(rotations.normalize(entry.pose[3:]))
            if entry.mesh is not None:
                local_normals, local_offsets = halfspaces(meshes[entry.mesh])
                world_normals = local_normals @ rotation.T
                normals.append(world_normals)
                offsets.append(local_offsets + world_normals @ entry.pose[:3])
            else:
                fields.append(_Field(rotation, entry.pose[:3].copy(), entry.heightfield))
        return cls(float(floor_z), normals, offsets, fields)

    @property
    def flat(self) -> bool:
        return not self.plane_normals and not self.fields

    def distance(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance [...] (negative inside) and unit normal [..., 3] of the nearest ground part at points."""
        distance = points[..., 2] - self.floor_z
        normal = torch.zeros_like(points)
        normal[..., 2] = 1.0
        for part_distance, part_normal in self._parts(points):
            closer = part_distance < distance
            distance = torch.where(closer, part_distance, distance)
            normal = torch.where(closer[..., None], part_normal, normal)
        return distance, normal

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        """The top of the ground [...] above points xy [..., 2]: the highest surface a body falling there meets."""
        like = {"dtype": xy.dtype, "device": xy.device}
        top = torch.full(xy.shape[:-1], self.floor_z, **like)
        for normals, offsets in zip(self.plane_normals, self.plane_offsets):
            normals_t, offsets_t = torch.as_tensor(normals, **like), torch.as_tensor(offsets, **like)
            # Along the vertical line through xy, plane p bounds z from above (n_z > 0) or below (n_z < 0) at
            # (d - n_xy . xy) / n_z; a vertical plane either admits the whole line or none of it.
            reach = offsets_t - xy @ normals_t[:, :2].T
            vertical = normals_t[:, 2].abs() < 1e-9
            bound = reach / torch.where(vertical, torch.ones_like(normals_t[:, 2]), normals_t[:, 2])
            inf = torch.full_like(bound, float("inf"))
            upper = torch.where(normals_t[:, 2] > 1e-9, bound, inf).amin(dim=-1)
            lower = torch.where(normals_t[:, 2] < -1e-9, bound, -inf).amax(dim=-1)
            crossed = (upper >= lower) & torch.where(vertical, reach >= 0, True).all(dim=-1)
            top = torch.where(crossed, torch.maximum(top, upper), top)
        for field in self.fields:
            rotation = field.rotation
            if abs(rotation[2, 2] - 1.0) > 1e-12:
                raise NotImplementedError("the height of a tilted height field")
            points = torch.cat([xy, torch.full_like(xy[..., :1], float(field.origin[2]))], dim=-1)
            distance, normal = self._field_distance(field, points)
            surface = field.origin[2] - distance / normal[..., 2]
            top = torch.where(torch.isfinite(distance), torch.maximum(top, surface), top)
        return top

    def _parts(self, points: torch.Tensor):
        like = {"dtype": points.dtype, "device": points.device}
        for normals, offsets in zip(self.plane_normals, self.plane_offsets):
            normals_t = torch.as_tensor(normals, **like)
            heights = points @ normals_t.T - torch.as_tensor(offsets, **like)
            distance, face = heights.max(dim=-1)
            yield distance, normals_t[face]
        for field in self.fields:
            yield self._field_distance(field, points)

    @staticmethod
    def _field_distance(field: _Field, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        like = {"dtype": points.dtype, "device": points.device}
        rotation = torch.as_tensor(field.rotation, **like)
        local = (points - torch.as_tensor(field.origin, **like)) @ rotation
        heights = torch.as_tensor(field.field.heights, **like)
        rows, columns = heights.shape
        size_x, size_y = field.field.size
        step_x, step_y = size_x / (columns - 1), size_y / (rows - 1)
        u = (local[..., 0] + size_x / 2) / step_x
        v = (local[..., 1] + size_y / 2) / step_y
        inside = (u >= 0) & (u <= columns - 1) & (v >= 0) & (v <= rows - 1)
        i = u.floor().clamp(0, columns - 2).long()
        j = v.floor().clamp(0, rows - 2).long()
        fu, fv = u - i, v - j
        h00, h10 = heights[j, i], heights[j, i + 1]
        h01, h11 = heights[j + 1, i], heights[j + 1, i + 1]
        # Lower triangle (fu >= fv): corners 00, 10, 11; upper: 00, 11, 01. Slopes per cell step.
        lower = fu >= fv
        slope_u = torch.where(lower, h10 - h00, h11 - h01)
        slope_v = torch.where(lower, h11 - h10, h01 - h00)
        surface = h00 + slope_u * fu + slope_v * fv
        gradient = torch.stack([-slope_u / step_x, -slope_v / step_y, torch.ones_like(slope_u)], dim=-1)
        local_normal = gradient / torch.linalg.vector_norm(gradient, dim=-1, keepdim=True)
        distance = (local[..., 2] - surface) * local_normal[..., 2]
        distance = torch.where(inside, distance, torch.full_like(distance, float("inf")))
        return distance, local_normal @ rotation.T


def signed_distance(ground: Ground, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`Ground.distance` for numpy points [..., 3] (float64)."""
    distance, normal = ground.distance(torch.from_numpy(np.ascontiguousarray(points, dtype=np.float64)))
    return distance.numpy(), normal.numpy()
