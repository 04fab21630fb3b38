"""The benchmark's convex solids (4 to 26 faces) as closed, outward-wound, centred, 10.48 cm wide meshes."""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import ConvexHull

from contactbench.meshes import Mesh

WIDTH = 0.1048  # m, largest extent of every solid's axis-aligned bounding box (paper, Section 3)
GOLDEN = (1.0 + np.sqrt(5.0)) / 2.0

SOLID_NAMES: dict[int, str] = {
    4: "tetrahedron",
    6: "cube",
    8: "octahedron",
    12: "dodecahedron",
    14: "truncated_octahedron",
    20: "icosahedron",
    26: "rhombicuboctahedron",
}


def _sign_combinations(point: tuple[float, float, float]) -> np.ndarray:
    """Every sign flip of a point's non-zero coordinates."""
    signs = itertools.product(*[(1.0, -1.0) if c else (1.0,) for c in point])
    return np.array([np.multiply(point, s) for s in signs])


def _cyclic(points: np.ndarray) -> np.ndarray:
    return np.concatenate([np.roll(points, shift, axis=1) for shift in range(3)])


def _all_permutations(points: np.ndarray) -> np.ndarray:
    return np.concatenate([points[:, list(order)] for order in itertools.permutations(range(3))])


def _corner_points(faces: int) -> np.ndarray:
    """Vertex coordinates of each solid (any scale and centre; duplicates allowed)."""
    cube = _sign_combinations((1.0, 1.0, 1.0))
    if faces == 4:
        return cube[np.prod(cube, axis=1) > 0]
    if faces == 6:
        return cube
    if faces == 8:
        return _cyclic(_sign_combinations((1.0, 0.0, 0.0)))
    if faces == 12:
        return np.concatenate([cube, _cyclic(_sign_combinations((0.0, 1.0 / GOLDEN, GOLDEN)))])
    if faces == 14:
        return _all_permutations(_sign_combinations((0.0, 1.0, 2.0)))
    if faces == 20:
        return _cyclic(_sign_combinations((0.0, 1.0, GOLDEN)))
    if faces == 26:
        return _all_permutations(_sign_combinations((1.0, 1.0, 1.0 + np.sqrt(2.0))))
    raise ValueError(f"no solid with {faces} faces; choose one of {sorted(SOLID_NAMES)}")


def convex_mesh(points: np.ndarray) -> Mesh:
    """The convex hull of points as a triangle mesh wound counter-clockwise seen from outside."""
    hull = ConvexHull(np.unique(points, axis=0))
    used = np.unique(hull.simplices)
    remap = np.full(len(hull.points), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    vertices = hull.points[used]
    faces = remap[hull.simplices]
    v0, v1, v2 = (vertices[faces[:, i]] for i in range(3))
    # Qhull orders simplex corners arbitrarily; flip those whose normal disagrees with the facet's outward normal.
    inward = np.einsum("ij,ij->i", np.cross(v1 - v0, v2 - v0), hull.equations[:, :3]) < 0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    return Mesh(vertices, faces)


def solid(faces: int, width: float = WIDTH) -> Mesh:
    """The convex solid with `faces` planar faces, centred at its centre of mass and scaled to `width`."""
    mesh = convex_mesh(_corner_points(faces))
    centre_of_mass, _ = mesh.mass_properties(1.0)
    vertices = (mesh.vertices - centre_of_mass) * (width / mesh.width)
    return Mesh(vertices, mesh.faces)
