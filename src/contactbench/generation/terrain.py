"""The TERRAIN family's static ground: a 10° ramp, a 5 cm step and a field of smooth bumps, as recordings entries."""

from __future__ import annotations

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.generation.solids import convex_mesh
from contactbench.meshes import Mesh

GROUNDS = ("ramp", "step", "bumps")
IDENTITY_POSE = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
RAMP_DEGREES = 10.0
RAMP_HALF_LENGTH = 1.0  # m: the ramp rises along +x from x = -1 m (on the floor) to x = +1 m
STEP_HEIGHT = 0.05  # m: the floor is raised over x > 0
BUMP_AMPLITUDE = 0.015  # m: bumps rise 0 .. 2 x amplitude above the floor
BUMP_WAVELENGTH = 0.32  # m
BUMP_EXTENT = 1.6  # m, square field centred on the origin
BUMP_SAMPLES = 81  # grid points per side (2 cm apart)
TAPER = 0.2  # m: the bumps fade into the floor over this margin at the field's edges


def _ramp() -> Mesh:
    rise = 2 * RAMP_HALF_LENGTH * np.tan(np.radians(RAMP_DEGREES))
    half = RAMP_HALF_LENGTH
    corners = [(x, y, 0.0) for x in (-half, half) for y in (-half, half)] + [(half, y, rise) for y in (-half, half)]
    return convex_mesh(np.array(corners))


def _step() -> Mesh:
    corners = [(x, y, z) for x in (0.0, 1.0) for y in (-1.0, 1.0) for z in (0.0, STEP_HEIGHT)]
    return convex_mesh(np.array(corners))


def _bumps() -> list[list[float]]:
    """Heights [rows along y][columns along x]: an egg-crate of smooth bumps, 0 at the field's edges."""
    axis = np.linspace(-BUMP_EXTENT / 2, BUMP_EXTENT / 2, BUMP_SAMPLES)
    x, y = np.meshgrid(axis, axis)
    wave = 1.0 + np.sin(2 * np.pi * x / BUMP_WAVELENGTH) * np.sin(2 * np.pi * y / BUMP_WAVELENGTH)
    margin = np.minimum(BUMP_EXTENT / 2 - np.abs(x), BUMP_EXTENT / 2 - np.abs(y))
    taper = np.sin(np.pi / 2 * np.clip(margin / TAPER, 0.0, 1.0)) ** 2
    return np.round(BUMP_AMPLITUDE * wave * taper, 12).tolist()


def terrain(ground: str) -> tuple[list[dict], dict[str, Mesh]]:
    """meta.json 'static' entries of a ground and the meshes they name (paths relative to the dataset folder)."""
    if ground == "ramp":
        return [{"name": "ramp", "mesh": "meshes/ramp.obj", "pose": IDENTITY_POSE}], {"meshes/ramp.obj": _ramp()}
    if ground == "step":
        return [{"name": "step", "mesh": "meshes/step.obj", "pose": IDENTITY_POSE}], {"meshes/step.obj": _step()}
    if ground == "bumps":
        field = {"heights": _bumps(), "size": [BUMP_EXTENT, BUMP_EXTENT]}
        return [{"name": "bumps", "heightfield": field, "pose": IDENTITY_POSE}], {}
    raise ContactbenchError(f"no ground {ground!r} (expected one of {list(GROUNDS)})")
