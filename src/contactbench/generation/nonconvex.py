"""The NONCONVEX family's bodies: L-bracket, U-channel, T and ring as unions of convex pieces, built with trimesh.

Each shape is a union of disjoint convex prisms (the hand split every engine collides, the same in all of them); its
true surface is their boolean union (manifold3d), checked watertight, its volume the pieces' sum. Shape and pieces
are moved into the union's principal frame (centre of mass at the origin, principal axes along x, y, z: PyBullet
and the recordings take a diagonal inertia there) and scaled to the benchmark's width of 10.48 cm.
"""

from __future__ import annotations

import numpy as np
import trimesh

from contactbench.errors import ContactbenchError
from contactbench.generation.solids import WIDTH
from contactbench.meshes import Mesh, closedness_problem

SHAPES = ("l_bracket", "u_channel", "t_beam", "ring")
_BAR = 0.3  # bar thickness in the plane, as a fraction of the shape's length
_DEPTH = 0.4  # extrusion depth, as a fraction of the shape's length
_RING_SECTORS = 12
_RING_INNER = 0.6  # inner radius / outer radius


def _box(low: tuple[float, float], high: tuple[float, float]) -> trimesh.Trimesh:
    """A prism over the rectangle low..high in the x-y plane, depth _DEPTH along z centred on z = 0."""
    extents = (high[0] - low[0], high[1] - low[1], _DEPTH)
    centre = ((high[0] + low[0]) / 2, (high[1] + low[1]) / 2, 0.0)
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(centre))


def _pieces(shape: str) -> list[trimesh.Trimesh]:
    """The disjoint convex pieces of a shape of unit length in the x-y plane."""
    bar = _BAR
    if shape == "l_bracket":
        return [_box((0.0, 0.0), (1.0, bar)), _box((0.0, bar), (bar, 0.7))]
    if shape == "u_channel":
        return [_box((0.0, 0.0), (1.0, bar)), _box((0.0, bar), (bar, 0.6)), _box((1.0 - bar, bar), (1.0, 0.6))]
    if shape == "t_beam":
        return [_box((0.0, 0.8 - bar), (1.0, 0.8)), _box((0.5 - bar / 2, 0.0), (0.5 + bar / 2, 0.8 - bar))]
    if shape == "ring":
        angles = np.linspace(0.0, 2 * np.pi, _RING_SECTORS + 1)
        pieces = []
        for start, stop in zip(angles[:-1], angles[1:]):
            corners = [
                0.5 * radius * np.array([np.cos(a), np.sin(a)]) for radius in (1.0, _RING_INNER) for a in (start, stop)
            ]
            points = [(*corner, z) for corner in corners for z in (-_DEPTH / 2, _DEPTH / 2)]
            pieces.append(trimesh.convex.convex_hull(np.array(points)))
        return pieces
    raise ContactbenchError(f"no non-convex shape {shape!r} (expected one of {list(SHAPES)})")


def _as_mesh(part: trimesh.Trimesh, what: str) -> Mesh:
    mesh = Mesh(np.asarray(part.vertices, dtype=np.float64), np.asarray(part.faces, dtype=np.int64))
    problem = closedness_problem(mesh.faces, len(mesh.vertices))
    if problem or not part.is_watertight or not part.is_volume:
        raise ContactbenchError(f"{what}: not a watertight solid ({problem or 'trimesh: not a volume'})")
    return mesh


def nonconvex_shape(shape: str, width: float = WIDTH) -> tuple[Mesh, list[Mesh]]:
    """The shape's true surface and its convex pieces, in its principal frame, `width` wide."""
    pieces = _pieces(shape)
    union = trimesh.boolean.union(pieces, engine="manifold")
    # manifold3d computes in single precision: its corners are the pieces' corners, so take those exactly.
    corners = np.concatenate([piece.vertices for piece in pieces])
    nearest = np.linalg.norm(union.vertices[:, None, :] - corners[None, :, :], axis=-1).argmin(axis=1)
    union = trimesh.Trimesh(corners[nearest], union.faces, process=False)
    if not union.is_watertight or abs(union.volume - sum(p.volume for p in pieces)) > 1e-9 * union.volume:
        raise ContactbenchError(f"shape {shape!r}: the union of its pieces is not one watertight solid of their volume")
    centre = union.center_mass
    inertia = union.moment_inertia
    if np.abs(inertia - np.diag(np.diag(inertia))).max() > 1e-12 * np.trace(inertia):
        _, axes = np.linalg.eigh(inertia)
        axes *= np.sign(axes[np.abs(axes).argmax(axis=0), range(3)])  # one sign per axis, whatever LAPACK returned
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1
    else:
        axes = np.eye(3)
    placed = [part.copy() for part in (union, *pieces)]
    transform = np.eye(4)
    transform[:3, :3] = axes.T
    transform[:3, 3] = -axes.T @ centre
    for part in placed:
        part.apply_transform(transform)
    scale = width / float(np.max(placed[0].extents))
    for part in placed:
        part.apply_scale(scale)
    return _as_mesh(placed[0], f"shape {shape!r}"), [
        _as_mesh(piece, f"shape {shape!r} piece {i}") for i, piece in enumerate(placed[1:])
    ]
