"""Triangle meshes: OBJ read/write, closedness check, mass properties and widths."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contactbench.errors import ContactbenchError


class MeshError(ContactbenchError):
    """A mesh file that is not a closed triangle mesh."""


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # [V, 3] float64, metres, mesh frame
    faces: np.ndarray  # [F, 3] int64, counter-clockwise seen from outside

    @property
    def width(self) -> float:
        """Largest extent of the axis-aligned bounding box (the paper's object width w_k)."""
        return float(np.max(self.vertices.max(axis=0) - self.vertices.min(axis=0)))

    @property
    def edges(self) -> np.ndarray:
        """Unique undirected edges [E, 2] (i < j)."""
        directed = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        return np.unique(np.sort(directed, axis=1), axis=0)

    def mass_properties(self, mass: float) -> tuple[np.ndarray, np.ndarray]:
        """Centre of mass [3] and inertia tensor [3, 3] about it, for uniform density and the given mass."""
        v0, v1, v2 = (self.vertices[self.faces[:, i]] for i in range(3))
        # Signed tetrahedra from the origin to each face (divergence theorem), exact for closed meshes.
        volumes = np.einsum("ij,ij->i", v0, np.cross(v1, v2)) / 6.0
        volume = volumes.sum()
        if volume <= 0:
            raise MeshError("mesh encloses no positive volume (faces inward or open)")
        com = (volumes[:, None] * (v0 + v1 + v2) / 4.0).sum(axis=0) / volume
        # Second moments of each tetrahedron: integral of x x^T over it (Tonon 2004 closed form).
        points = np.stack([v0, v1, v2], axis=1)  # [F, 3 corners, 3]
        summed = points.sum(axis=1)
        per_face = np.einsum("fci,fcj->fij", points, points) + np.einsum("fi,fj->fij", summed, summed)
        covariance = np.einsum("f,fij->ij", volumes / 20.0, per_face)
        density = mass / volume
        second_moment = density * covariance - mass * np.outer(com, com)
        inertia = np.trace(second_moment) * np.eye(3) - second_moment
        return com, inertia


def convexity_problem(mesh: Mesh, tolerance: float = 1e-6) -> str | None:
    """Why a closed mesh is not convex (a vertex farther than `tolerance` widths outside a face's plane), or None.

    Engines collide what they are given as convex hulls; a piece or static mesh that is not convex would collide as a
    different solid than the one the recordings describe."""
    v0, v1, v2 = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    normals = np.cross(v1 - v0, v2 - v0)
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 1e-12 * mesh.width**2
    normals = normals[keep] / lengths[keep, None]
    outside = np.einsum("fj,vj->fv", normals, mesh.vertices) - np.einsum("fj,fj->f", normals, v0[keep])[:, None]
    worst = float(outside.max()) if outside.size else 0.0
    if worst > tolerance * mesh.width:
        return f"not convex (a vertex lies {worst:.3g} m outside a face's plane)"
    return None


def closedness_problem(faces: np.ndarray, n_vertices: int) -> str | None:
    """Why a face list is not a closed, consistently oriented triangle mesh, or None if it is."""
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 4:
        return "needs at least 4 triangular faces"
    if faces.min() < 0 or faces.max() >= n_vertices:
        return "a face refers to a vertex that does not exist"
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    if np.any(directed[:, 0] == directed[:, 1]):
        return "a face repeats a vertex"
    keys = directed[:, 0] * n_vertices + directed[:, 1]
    unique_keys, counts = np.unique(keys, return_counts=True)
    if np.any(counts > 1):
        return "an edge is used twice in the same direction (non-manifold or inconsistent winding)"
    reverse = directed[:, 1] * n_vertices + directed[:, 0]
    if not np.all(np.isin(reverse, unique_keys)):
        return "an edge has only one face (the mesh has a hole)"
    return None


def read_obj(path: str | os.PathLike) -> Mesh:
    """Read the vertices and faces of an OBJ file; polygons are fanned into triangles."""
    path = Path(path)
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as error:
        raise MeshError(f"{path}: cannot read mesh ({error.strerror})") from None
    except UnicodeDecodeError as error:
        raise MeshError(
            f"{path}: not a text OBJ file (byte {error.start} is not UTF-8; expected 'v x y z' and 'f i j k' lines)"
        ) from None
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        try:
            if fields[0] == "v":
                if len(fields) < 4:
                    raise ValueError
                vertices.append([float(x) for x in fields[1:4]])
            elif fields[0] == "f":
                indices = [int(token.split("/")[0]) for token in fields[1:]]
                indices = [i - 1 if i > 0 else len(vertices) + i for i in indices]
                faces.extend([indices[0], indices[i], indices[i + 1]] for i in range(1, len(indices) - 1))
        except ValueError:
            raise MeshError(f"{path}: line {number}: cannot parse {line.strip()!r}") from None
    outside = next((i for face in faces for i in face if not 0 <= i < len(vertices)), None)
    if outside is not None:
        raise MeshError(
            f"{path}: a face refers to vertex {outside + 1} (expected 1..{len(vertices)}, the file's 'v' lines)"
        )
    vertex_array = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    face_array = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not np.all(np.isfinite(vertex_array)):
        raise MeshError(f"{path}: vertices must be finite numbers")
    problem = closedness_problem(face_array, len(vertex_array))
    if problem:
        raise MeshError(f"{path}: not a closed triangle mesh: {problem}")
    return Mesh(vertex_array, face_array)


def obj_text(mesh: Mesh, comment: str = "") -> str:
    lines = [f"# {comment}"] if comment else []
    lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    return "\n".join(lines) + "\n"
