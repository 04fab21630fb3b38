"""Toss scene variants (paper Table 2b; Table 2a's engine settings are the world's, sim/bullet_world.py) and sampling
of non-overlapping initial states."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.generation.nonconvex import SHAPES
from contactbench.generation.solids import SOLID_NAMES
from contactbench.generation.terrain import GROUNDS
from contactbench.ground import Ground
from contactbench.meshes import Mesh
from contactbench.values import set_floats, set_vectors

ELBOW = "elbow"  # the ARTICULATED family's two-link body (articulated.py)


class SpawnError(RuntimeError):
    """A body could not be placed without overlapping the bodies placed before it."""


@dataclass(frozen=True)
class SceneSpec:
    """One scene variant: object material, shape and count, and the initial-state distribution (Table 2b)."""

    name: str  # dataset name, e.g. "frictioncubes"
    friction: float
    restitution: float
    faces: int = 6  # which solid (6 = cube), see solids.SOLID_NAMES
    bodies: int = 1
    shape: str = ""  # a non-convex body (nonconvex.SHAPES) or the two-link "elbow"; "" = the solid with `faces` faces
    ground: str = "flat"  # the floor alone, or a terrain on it (terrain.GROUNDS)
    joint_damping: float = 0.0  # N m s/rad in the elbow's hinge
    center_bias_speed: float = (
        0.0  # m/s subtracted from each body's xy velocity along its direction from the centre; 0 disables
    )
    position_low: tuple[float, float, float] = (-0.4, -0.4, 0.13)
    position_high: tuple[float, float, float] = (0.4, 0.4, 0.15)
    velocity_low: tuple[float, float, float] = (-1.2, -1.2, 0.0)
    velocity_high: tuple[float, float, float] = (1.2, 1.2, 0.0)
    spawn_attempts: int = 100

    def __post_init__(self) -> None:
        # Hydra hands over ints where floats are meant and ListConfigs where tuples are; normalise so the
        # spec hashes, compares and serialises the same however it was built.
        for key in ("name", "shape", "ground"):
            object.__setattr__(self, key, str(getattr(self, key)))
        set_floats(self, "friction", "restitution", "center_bias_speed", "joint_damping")
        set_vectors(self, "position_low", "position_high", "velocity_low", "velocity_high")
        for key in ("faces", "bodies", "spawn_attempts"):
            object.__setattr__(self, key, int(getattr(self, key)))
        # Physically meaningless values would still simulate (PyBullet takes them) and score: refuse them here.
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise ContactbenchError(
                f"scene {self.name!r}: friction is {self.friction:g} (expected a friction coefficient >= 0)"
            )
        if not (0 <= self.restitution <= 1):
            raise ContactbenchError(
                f"scene {self.name!r}: restitution is {self.restitution:g} (expected a coefficient from 0 to 1)"
            )
        if not (math.isfinite(self.center_bias_speed) and self.center_bias_speed >= 0):
            raise ContactbenchError(
                f"scene {self.name!r}: center_bias_speed is {self.center_bias_speed:g} (expected a speed >= 0 in m/s)"
            )
        if self.faces not in SOLID_NAMES:
            raise ContactbenchError(
                f"scene {self.name!r}: faces is {self.faces} (expected one of {sorted(SOLID_NAMES)})"
            )
        if self.shape and self.shape not in (*SHAPES, ELBOW):
            raise ContactbenchError(
                f"scene {self.name!r}: shape is {self.shape!r} (expected one of {[*SHAPES, ELBOW]})"
            )
        if (self.shape == ELBOW and self.bodies != 2) or (self.joint_damping and self.shape != ELBOW):
            raise ContactbenchError(
                f"scene {self.name!r}: the elbow has bodies 2 (its links) and only it has joint damping; got bodies "
                f"{self.bodies}, shape {self.shape!r}, joint_damping {self.joint_damping:g}"
            )
        if not (math.isfinite(self.joint_damping) and self.joint_damping >= 0):
            raise ContactbenchError(
                f"scene {self.name!r}: joint_damping is {self.joint_damping:g} (expected N m s/rad >= 0)"
            )
        if self.ground != "flat" and self.ground not in GROUNDS:
            raise ContactbenchError(
                f"scene {self.name!r}: ground is {self.ground!r} (expected 'flat' or one of {list(GROUNDS)})"
            )
        if self.bodies < 1:
            raise ContactbenchError(f"scene {self.name!r}: bodies is {self.bodies} (expected at least 1)")
        if self.spawn_attempts < 1:
            raise ContactbenchError(
                f"scene {self.name!r}: spawn_attempts is {self.spawn_attempts} (expected at least 1)"
            )
        if np.any(np.greater(self.position_low, self.position_high)) or np.any(
            np.greater(self.velocity_low, self.velocity_high)
        ):
            raise ValueError(f"scene {self.name!r}: a lower bound of the initial-state box exceeds its upper bound")


def sample_initial_state(
    spec: SceneSpec, mesh: Mesh, rng: np.random.Generator, ground: Ground | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Initial poses [K, 7] (position, quaternion w-first) and velocities [K, 6] (linear, angular; world frame).

    Over a terrain (`ground`), heights are drawn above the highest ground under the body's footprint, so a toss
    starts as high above the terrain as it would above the floor."""
    if spec.bodies == 1:
        orientation = rotations.uniform_random(rng, 1)[0]
        position = rng.uniform(spec.position_low, spec.position_high)
        poses = np.concatenate([position, orientation])[None]
    else:
        poses = _spawn_without_overlap(spec, mesh, rng)
    if ground is not None and not ground.flat:
        poses[:, 2] += [_ground_under(ground, mesh, pose) - ground.floor_z for pose in poses]
    linear = rng.uniform(spec.velocity_low, spec.velocity_high, size=(spec.bodies, 3))
    if spec.center_bias_speed > 0:
        centre = (np.asarray(spec.position_low[:2]) + np.asarray(spec.position_high[:2])) / 2.0
        offset = poses[:, :2] - centre
        distance = np.linalg.norm(offset, axis=1, keepdims=True)
        # A body exactly at the centre has no direction to be biased along.
        direction = np.divide(offset, distance, out=np.zeros_like(offset), where=distance > 0)
        linear[:, :2] -= spec.center_bias_speed * direction
    velocities = np.concatenate([linear, np.zeros((spec.bodies, 3))], axis=1)
    return poses, velocities


def _ground_under(ground: Ground, mesh: Mesh, pose: np.ndarray, samples: int = 7) -> float:
    """The highest ground under the x-y box of the mesh at `pose` (a grid of samples, and the vertices)."""
    placed = pose[:3] + rotations.rotate(pose[3:], mesh.vertices)
    low, high = placed[:, :2].min(axis=0), placed[:, :2].max(axis=0)
    grid = np.stack(np.meshgrid(*(np.linspace(a, b, samples) for a, b in zip(low, high))), axis=-1).reshape(-1, 2)
    points = torch.from_numpy(np.concatenate([grid, placed[:, :2]]))
    return float(ground.height(points).max())


def _spawn_without_overlap(spec: SceneSpec, mesh: Mesh, rng: np.random.Generator) -> np.ndarray:
    """Iterative spawning after Greff et al. (2022, Kubric): each body gets a fresh rotation and position
    until its axis-aligned box overlaps none of the boxes placed before it."""
    low = np.asarray(spec.position_low)
    high = np.asarray(spec.position_high)
    poses = np.empty((spec.bodies, 7))
    boxes_low = np.empty((spec.bodies, 3))
    boxes_high = np.empty((spec.bodies, 3))
    # Sampling runs inside the generator's workers, next to the engine: array methods and in-place updates
    # keep the numpy call overhead of each attempt down.
    for body in range(spec.bodies):
        placed_low, placed_high = boxes_low[:body], boxes_high[:body]
        for _ in range(spec.spawn_attempts):
            orientation = rotations.uniform_random(rng, 1)[0]
            rotated = rotations.rotate(orientation, mesh.vertices)
            extent_low, extent_high = rotated.min(axis=0), rotated.max(axis=0)
            # x, y: the whole box stays inside the spawn region. z: the region (2 cm) is thinner than any object,
            # so, as for a single body, the centre's height is drawn from the region itself.
            centre_low, centre_high = low.copy(), high.copy()
            centre_low[:2] -= extent_low[:2]
            centre_high[:2] -= extent_high[:2]
            if (centre_low > centre_high).any():
                continue
            position = rng.uniform(centre_low, centre_high)
            box_low, box_high = position + extent_low, position + extent_high
            if not ((box_low < placed_high) & (placed_low < box_high)).all(axis=1).any():
                break
        else:
            raise SpawnError(
                f"body {body} of {spec.bodies} could not be placed without overlapping the bodies before it "
                f"in {spec.spawn_attempts} attempts (scene {spec.name!r}, spawn region "
                f"{spec.position_low}..{spec.position_high})"
            )
        poses[body, :3], poses[body, 3:] = position, orientation
        boxes_low[body], boxes_high[body] = box_low, box_high
    return poses
