"""An independent PyBullet generator of toss datasets with concealed effects, for a blind test of diagnose.py.

    python benchmarks/independent_generator.py benchmarks/proof_sets/independent_1.yaml [--record-sizes]

Notes:
- Written from scratch, without reading how the diagnosis library or the project's own generator model effects: the
  only shared code is the recordings writer, the meshes and the solids. A case is a dict (shape, effect, strength,
  seed, velocities); `generate_case` writes its dataset and `size` measures how far the effect moves the body.
- One convex body (zero collision margin, so it touches the floor with its mesh) tossed onto a floor plane in
  PyBullet DIRECT mode, stepped 7 times per frame; 140 frames per toss at the benchmark's dt; splits 275/165/110.
- All contact material lives on the floor (friction 0.5, restitution 0.1, rolling, spinning, anisotropy, stiffness);
  the body's own friction and restitution are 1, and Bullet multiplies the two, so the floor's values are the contact's.
- The recordings always describe the nominal world: flat floor at z = 0, gravity 9.8 m/s^2 down, a uniform-density
  body whose centre of mass is the mesh centroid. An effect changes the simulated world only.
- Every toss runs in a freshly reset world, and its initial state is drawn from (seed, split, toss) alone, so a case
  and its null twin (same case, effect off) start every toss identically; effect-only randomness (gust direction,
  floor phase) comes from a separate stream. Folder names are digests of the case, so they do not reveal the effect.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pybullet
import yaml

from contactbench import rotations
from contactbench.generation.solids import SOLID_NAMES, WIDTH, convex_mesh, solid
from contactbench.meshes import Mesh
from contactbench.metrics import position_error
from contactbench.recordings import read_meta, read_recordings, write_recordings
from contactbench.scene import FORMAT, VERSION, Recordings, Split

DT = 0.00676  # s between frames: the benchmark's generated datasets (frictioncubes meta.json)
SUBSTEPS = 7  # physics steps per frame: a 0.97 ms (about 1 kHz) PyBullet step
FRAMES = 140
SPLIT_SIZES = {"train": 275, "val": 165, "test": 110}
GRAVITY = 9.8  # m/s^2, as recorded
CUBE_MASS = 0.37  # kg, the benchmark's cube; every body has the cube's density
DENSITY = CUBE_MASS / WIDTH**3
FRICTION = 0.5
RESTITUTION = 0.1

# Box bodies: extents as fractions of the benchmark width along mesh x, y, z.
BOX_EXTENTS = {"cube": (1.0, 1.0, 1.0), "plate": (1.0, 0.75, 0.17), "brick": (1.0, 0.5, 0.33)}
POLYHEDRON_FACES = {name: faces for faces, name in SOLID_NAMES.items() if name != "cube"}

# Initial states (own choice, in the spirit of the benchmark's tosses): centre 0.1-0.5 m up, any orientation.
SPAWN_HALF_SPAN = 0.15  # m, horizontal start inside a 30 cm square around the origin
SPAWN_HEIGHT = (0.1, 0.5)  # m, centre above the nominal floor
SPAWN_CLEARANCE = 0.02  # m, lowest vertex above the floor at least this (room for offset, tilted and moving floors)
HORIZONTAL_SPEED = 1.5  # m/s, most
VERTICAL_SPEED = (-1.0, 0.5)  # m/s
SPIN = 4.0  # rad/s, most per axis

# Effect constants (strength is each effect's one free parameter).
AIR_DRAG_PER_METRE = 0.5  # 1/m: acceleration = this |u| u for air velocity u relative to the body (wind, gusts)
WIND_AZIMUTH = math.radians(30.0)
GUST_PERIOD = 0.6  # s between gust peaks
SWIRL_RADIUS = 0.1  # m: the swirl field's acceleration is `strength` m/s^2 at this distance from its axis
STRIBECK_SPEED = 0.1  # m/s: slip speed over which friction falls from static to kinetic
TILE_CENTRE = (0.2, 0.0)  # m
TILE_HALF_SIZE = 0.2  # m: a 40 cm square tile beside the spawn area, crossed by about half the tosses
FLOOR_WAVE_HZ = 1.2
SOFT_FLOOR_DAMPING_RATIO = 1.0  # critically damped: the soft floor yields, but rebounds no more than the rigid one
COM_DIRECTION = np.array([2.0, 1.0, -1.0]) / math.sqrt(6.0)  # mesh frame; scaled by the body's half extents
TILT_AXIS_AZIMUTH = math.radians(60.0)  # the floor tilts about this horizontal axis


@dataclass(frozen=True)
class BodyModel:
    name: str
    mesh: Mesh  # centred at its uniform-density centre of mass
    mass: float
    inertia_diagonal: tuple[float, float, float]  # uniform density, about the centroid along mesh axes
    half_extents: np.ndarray  # [3] of the mesh's bounding box


@dataclass(frozen=True)
class InitialState:
    """Of the mesh frame, world frame: position (m), quaternion w x y z, velocity (m/s), angular velocity (rad/s)."""

    position: np.ndarray
    orientation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray


def _volume(mesh: Mesh) -> float:
    v0, v1, v2 = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0)


@functools.cache
def body_model(shape: str) -> BodyModel:
    if shape in BOX_EXTENTS:
        corners = np.array(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [-0.5, 0.5])).reshape(3, -1).T
        mesh = convex_mesh(corners * np.array(BOX_EXTENTS[shape]) * WIDTH)
    elif shape in POLYHEDRON_FACES:
        mesh = solid(POLYHEDRON_FACES[shape])
    else:
        raise ValueError(f"unknown shape {shape!r} (expected one of {sorted(BOX_EXTENTS) + sorted(POLYHEDRON_FACES)})")
    mass = DENSITY * _volume(mesh)
    _, inertia = mesh.mass_properties(mass)
    # Boxes, and solids with a cube's or icosahedron's symmetry, have principal axes along the mesh axes: the
    # diagonal is the whole tensor.
    half_extents = (mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)) / 2.0
    return BodyModel(shape, mesh, mass, tuple(float(x) for x in np.diag(inertia)), half_extents)


@dataclass(frozen=True)
class Physics:
    """The world a toss is simulated in; the defaults are the nominal world the recordings describe."""

    gravity: float = GRAVITY
    floor_height: float = 0.0
    floor_tilt: float = 0.0  # rad about the horizontal axis at TILT_AXIS_AZIMUTH
    floor_anisotropy: tuple[float, float, float] = (1.0, 1.0, 1.0)  # Bullet's per-axis friction scale, floor frame
    floor_stiffness: tuple[float, float] | None = None  # (N/m, N s/m) per contact point; None = rigid
    rolling_friction: float = 0.0  # m
    spinning_friction: float = 0.0  # m
    com_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, mesh frame
    inertia_scale: float = 1.0


@functools.cache
def _client() -> int:
    return pybullet.connect(pybullet.DIRECT)


class TossWorld:
    """One PyBullet world, reset for one toss: a floor plane and the body, placed at a mesh-frame state."""

    def __init__(self, body: BodyModel, physics: Physics, initial: InitialState):
        self.client = client = _client()
        self.mass = body.mass
        self.com_offset = np.array(physics.com_offset)
        pybullet.resetSimulation(physicsClientId=client)
        pybullet.setPhysicsEngineParameter(
            fixedTimeStep=DT / SUBSTEPS, deterministicOverlappingPairs=1, physicsClientId=client
        )
        pybullet.setGravity(0.0, 0.0, -physics.gravity, physicsClientId=client)
        tilt_axis = [math.cos(TILT_AXIS_AZIMUTH), math.sin(TILT_AXIS_AZIMUTH), 0.0]
        self.floor_orientation = pybullet.getQuaternionFromAxisAngle(tilt_axis, physics.floor_tilt)
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client)
        self.floor = pybullet.createMultiBody(
            0.0,
            plane,
            basePosition=[0.0, 0.0, physics.floor_height],
            baseOrientation=self.floor_orientation,
            physicsClientId=client,
        )
        stiffness = {}
        if physics.floor_stiffness is not None:
            stiffness = {"contactStiffness": physics.floor_stiffness[0], "contactDamping": physics.floor_stiffness[1]}
        self.set_floor(
            lateralFriction=FRICTION,
            restitution=RESTITUTION,
            rollingFriction=physics.rolling_friction,
            spinningFriction=physics.spinning_friction,
            anisotropicFriction=list(physics.floor_anisotropy),
            **stiffness,
        )
        hull = pybullet.createCollisionShape(
            pybullet.GEOM_MESH, vertices=body.mesh.vertices.tolist(), physicsClientId=client
        )
        self.body = pybullet.createMultiBody(
            body.mass, hull, baseInertialFramePosition=list(physics.com_offset), physicsClientId=client
        )
        pybullet.changeDynamics(
            self.body,
            -1,
            lateralFriction=1.0,
            restitution=1.0,
            # PyBullet damps every body by default; the nominal world has no damping at all.
            linearDamping=0.0,
            angularDamping=0.0,
            # Bullet computes a hull's inertia from its bounding box: set the uniform solid's (or the effect's).
            localInertiaDiagonal=[physics.inertia_scale * x for x in body.inertia_diagonal],
            # A zero margin makes the hull touch the floor with its vertices, not 1 mm outside them.
            collisionMargin=0.0,
            # A sleeping body ignores applied forces and a moving floor.
            activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING,
            physicsClientId=client,
        )
        # PyBullet places and moves the centre of mass, not the mesh frame.
        com_world = rotations.rotate(initial.orientation, self.com_offset)
        position = initial.position + com_world
        velocity = initial.velocity + np.cross(initial.angular_velocity, com_world)
        w, x, y, z = initial.orientation
        pybullet.resetBasePositionAndOrientation(self.body, position.tolist(), [x, y, z, w], physicsClientId=client)
        pybullet.resetBaseVelocity(
            self.body, velocity.tolist(), initial.angular_velocity.tolist(), physicsClientId=client
        )

    def centre_of_mass(self) -> tuple[float, float, float]:
        return pybullet.getBasePositionAndOrientation(self.body, physicsClientId=self.client)[0]

    def velocity(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Linear velocity of the centre of mass and angular velocity, world frame."""
        return pybullet.getBaseVelocity(self.body, physicsClientId=self.client)

    def push(self, force: tuple[float, float, float] | np.ndarray) -> None:
        """A force through the centre of mass for the next step (PyBullet clears applied forces after each step)."""
        pybullet.applyExternalForce(
            self.body, -1, list(force), self.centre_of_mass(), pybullet.WORLD_FRAME, physicsClientId=self.client
        )

    def set_floor(self, **dynamics: float | list[float]) -> None:
        pybullet.changeDynamics(self.floor, -1, physicsClientId=self.client, **dynamics)

    def move_floor(self, height: float) -> None:
        pybullet.resetBasePositionAndOrientation(
            self.floor, [0.0, 0.0, height], self.floor_orientation, physicsClientId=self.client
        )

    def slip_speed(self) -> float | None:
        """Mean tangential speed of the body's points touching the floor, or None out of contact."""
        contacts = pybullet.getContactPoints(self.body, self.floor, physicsClientId=self.client)
        if not contacts:
            return None
        # Plain floats: this runs every physics step, where numpy's per-call overhead tripled the case's time.
        cx, cy, cz = self.centre_of_mass()
        (vx, vy, vz), (wx, wy, wz) = self.velocity()
        total = 0.0
        for contact in contacts:
            px, py, pz = contact[5]
            nx, ny, nz = contact[7]
            rx, ry, rz = px - cx, py - cy, pz - cz
            ux, uy, uz = vx + wy * rz - wz * ry, vy + wz * rx - wx * rz, vz + wx * ry - wy * rx
            normal_speed = ux * nx + uy * ny + uz * nz
            total += math.sqrt(max(0.0, ux * ux + uy * uy + uz * uz - normal_speed * normal_speed))
        return total / len(contacts)

    def step(self) -> None:
        pybullet.stepSimulation(physicsClientId=self.client)

    def mesh_frame_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Centre-of-mass position, quaternion w x y z, centre-of-mass velocity, angular velocity (world)."""
        position, (x, y, z, w) = pybullet.getBasePositionAndOrientation(self.body, physicsClientId=self.client)
        linear, angular = self.velocity()
        return np.array(position), np.array([w, x, y, z]), np.array(linear), np.array(angular)


# ---------------------------------------------------------------- effects


class Effect:
    """A concealed change to a toss's physics: a different world (`physics`) and/or per-step actions."""

    def __init__(self, strength: float, rng: np.random.Generator):
        self.strength = strength

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        return nominal

    def before_step(self, world: TossWorld, time: float) -> None:
        """Forces or contact changes for the physics step starting at `time` (s since the toss began)."""


class LinearDrag(Effect):
    """Viscous drag: acceleration -strength v (strength in 1/s)."""

    def before_step(self, world: TossWorld, time: float) -> None:
        velocity = np.array(world.velocity()[0])
        world.push(-self.strength * world.mass * velocity)


class QuadraticDrag(Effect):
    """Aerodynamic drag in still air: acceleration -strength |v| v (strength in 1/m)."""

    def before_step(self, world: TossWorld, time: float) -> None:
        velocity = np.array(world.velocity()[0])
        world.push(-self.strength * world.mass * np.linalg.norm(velocity) * velocity)


class MovingAir(Effect):
    """Quadratic drag relative to air moving at `air_velocity(time)`."""

    def air_velocity(self, time: float) -> np.ndarray:
        raise NotImplementedError

    def before_step(self, world: TossWorld, time: float) -> None:
        relative = self.air_velocity(time) - np.array(world.velocity()[0])
        world.push(AIR_DRAG_PER_METRE * world.mass * np.linalg.norm(relative) * relative)


class SteadyWind(MovingAir):
    """A steady horizontal wind of `strength` m/s from a fixed direction."""

    def air_velocity(self, time: float) -> np.ndarray:
        return self.strength * np.array([math.cos(WIND_AZIMUTH), math.sin(WIND_AZIMUTH), 0.0])


class Gusts(MovingAir):
    """Gusts peaking at `strength` m/s every GUST_PERIOD, calm between; direction and timing differ per toss."""

    def __init__(self, strength: float, rng: np.random.Generator):
        super().__init__(strength, rng)
        azimuth, self.phase = rng.uniform(0.0, 2.0 * math.pi, size=2)
        self.direction = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])

    def air_velocity(self, time: float) -> np.ndarray:
        return self.strength * math.sin(math.pi * time / GUST_PERIOD + self.phase) ** 2 * self.direction


class SwirlField(Effect):
    """A horizontal force field circling the vertical axis through the origin, growing with distance from it."""

    def before_step(self, world: TossWorld, time: float) -> None:
        x, y, _ = world.centre_of_mass()
        scale = self.strength * world.mass / SWIRL_RADIUS
        world.push((-scale * y, scale * x, 0.0))


class StribeckFriction(Effect):
    """Friction that falls with slip speed: mu(v) from 0.5 (1 + s) at rest to 0.5 / (1 + s) when sliding fast."""

    def __init__(self, strength: float, rng: np.random.Generator):
        super().__init__(strength, rng)
        self.static = FRICTION * (1.0 + strength)
        self.kinetic = FRICTION / (1.0 + strength)

    def before_step(self, world: TossWorld, time: float) -> None:
        slip = world.slip_speed()
        if slip is not None:
            friction = self.kinetic + (self.static - self.kinetic) * math.exp(-((slip / STRIBECK_SPEED) ** 2))
            world.set_floor(lateralFriction=friction)


class FloorTile(Effect):
    """A square of floor with other contact material, applied while the body's centre is above it."""

    def __init__(self, strength: float, rng: np.random.Generator):
        super().__init__(strength, rng)
        self.on_tile = False

    def tile_material(self) -> dict[str, float]:
        raise NotImplementedError

    def before_step(self, world: TossWorld, time: float) -> None:
        x, y, _ = world.centre_of_mass()
        on_tile = max(abs(x - TILE_CENTRE[0]), abs(y - TILE_CENTRE[1])) <= TILE_HALF_SIZE
        if on_tile != self.on_tile:
            self.on_tile = on_tile
            world.set_floor(
                **(self.tile_material() if on_tile else {"lateralFriction": FRICTION, "restitution": RESTITUTION})
            )


class SlipperyTile(FloorTile):
    """A tile with friction 0.5 / (1 + strength)."""

    def tile_material(self) -> dict[str, float]:
        return {"lateralFriction": FRICTION / (1.0 + self.strength)}


class BouncyTile(FloorTile):
    """A tile with restitution 0.1 + strength (at most 0.95)."""

    def tile_material(self) -> dict[str, float]:
        return {"restitution": min(0.95, RESTITUTION + self.strength)}


class MovingFloor(Effect):
    """The floor bobs up and down by `strength` m at FLOOR_WAVE_HZ, with a phase that differs per toss."""

    def __init__(self, strength: float, rng: np.random.Generator):
        super().__init__(strength, rng)
        self.phase = rng.uniform(0.0, 2.0 * math.pi)

    def before_step(self, world: TossWorld, time: float) -> None:
        world.move_floor(self.strength * math.sin(2.0 * math.pi * FLOOR_WAVE_HZ * time + self.phase))


class AnisotropicFriction(Effect):
    """Bullet's anisotropic friction on the floor: friction along world y scaled by 1 / (1 + strength)."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        return replace(nominal, floor_anisotropy=(1.0, 1.0 / (1.0 + self.strength), 1.0))


class SpinningFriction(Effect):
    """Bullet's torsional friction: a torque up to strength (m) times the normal force, against spin."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        return replace(nominal, spinning_friction=self.strength)


class RollingFriction(Effect):
    """Bullet's rolling friction: a torque up to strength (m) times the normal force, against rolling."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        return replace(nominal, rolling_friction=self.strength)


class SoftFloor(Effect):
    """A compliant floor: a contact point would sink `strength` mm under the body's weight alone."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        stiffness = body.mass * GRAVITY / (self.strength * 1e-3)
        damping = 2.0 * SOFT_FLOOR_DAMPING_RATIO * math.sqrt(stiffness * body.mass)
        return replace(nominal, floor_stiffness=(stiffness, damping))


class FloorOffset(Effect):
    """The floor `strength` m above the recorded floor_z (negative: below)."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        return replace(nominal, floor_height=self.strength)


class FloorTilt(Effect):
    """The floor tilted by `strength` degrees about a horizontal axis through the origin."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        return replace(nominal, floor_tilt=math.radians(self.strength))


class GravityScale(Effect):
    """Gravity (1 + strength) times the recorded gravity."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        return replace(nominal, gravity=GRAVITY * (1.0 + self.strength))


class ComOffset(Effect):
    """The centre of mass moved `strength` of the way from the centroid toward a corner of the bounding box."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        offset = self.strength * body.half_extents * COM_DIRECTION
        return replace(nominal, com_offset=tuple(float(x) for x in offset))


class InertiaScale(Effect):
    """Every principal moment (1 + strength) times the uniform solid's: mass toward the surface (or the core)."""

    def physics(self, nominal: Physics, body: BodyModel) -> Physics:
        return replace(nominal, inertia_scale=1.0 + self.strength)


EFFECTS: dict[str, Callable[[float, np.random.Generator], Effect]] = {
    "linear_drag": LinearDrag,
    "quadratic_drag": QuadraticDrag,
    "wind": SteadyWind,
    "gusts": Gusts,
    "swirl_field": SwirlField,
    "stribeck_friction": StribeckFriction,
    "slippery_tile": SlipperyTile,
    "bouncy_tile": BouncyTile,
    "moving_floor": MovingFloor,
    "anisotropic_friction": AnisotropicFriction,
    "spinning_friction": SpinningFriction,
    "rolling_friction": RollingFriction,
    "soft_floor": SoftFloor,
    "floor_offset": FloorOffset,
    "floor_tilt": FloorTilt,
    "gravity_scale": GravityScale,
    "com_offset": ComOffset,
    "inertia_scale": InertiaScale,
}


# ---------------------------------------------------------------- tosses


def initial_state(body: BodyModel, rng: np.random.Generator) -> InitialState:
    orientation = rotations.normalize(rng.normal(size=4))  # uniform over rotations
    position = np.array([*rng.uniform(-SPAWN_HALF_SPAN, SPAWN_HALF_SPAN, size=2), rng.uniform(*SPAWN_HEIGHT)])
    lowest = position[2] + rotations.rotate(orientation, body.mesh.vertices)[:, 2].min()
    position[2] += max(0.0, SPAWN_CLEARANCE - lowest)
    azimuth = rng.uniform(0.0, 2.0 * math.pi)
    speed = rng.uniform(0.0, HORIZONTAL_SPEED)
    velocity = np.array([speed * math.cos(azimuth), speed * math.sin(azimuth), rng.uniform(*VERTICAL_SPEED)])
    return InitialState(position, orientation, velocity, rng.uniform(-SPIN, SPIN, size=3))


def simulate_toss(
    body: BodyModel, effect_name: str | None, strength: float, seed: int, split_number: int, toss: int
) -> tuple[np.ndarray, np.ndarray]:
    """One toss's mesh-frame poses [FRAMES, 7] and velocities [FRAMES, 6]; effect None is the nominal world."""
    state_seed, effect_seed = np.random.SeedSequence([seed, split_number, toss]).spawn(2)
    initial = initial_state(body, np.random.default_rng(state_seed))
    effect = Effect(0.0, np.random.default_rng(effect_seed))
    if effect_name is not None:
        effect = EFFECTS[effect_name](strength, np.random.default_rng(effect_seed))
    world = TossWorld(body, effect.physics(Physics(), body), initial)
    com = np.empty((FRAMES, 3))
    orientation = np.empty((FRAMES, 4))
    com_velocity = np.empty((FRAMES, 3))
    angular = np.empty((FRAMES, 3))
    step_time = DT / SUBSTEPS
    for frame in range(FRAMES):
        if frame:
            for substep in range(SUBSTEPS):
                effect.before_step(world, ((frame - 1) * SUBSTEPS + substep) * step_time)
                world.step()
        com[frame], orientation[frame], com_velocity[frame], angular[frame] = world.mesh_frame_state()
    com_world = rotations.rotate(orientation, world.com_offset)  # mesh origin = centre of mass - R c
    poses = np.concatenate([com - com_world, orientation], axis=1)
    velocities = np.concatenate([com_velocity - np.cross(angular, com_world), angular], axis=1)
    return poses, velocities


# ---------------------------------------------------------------- datasets


def _effective(case: dict, with_effect: bool) -> tuple[str | None, float]:
    effect = case.get("effect") if with_effect else None
    if effect is not None and effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r} (expected one of {sorted(EFFECTS)})")
    return effect, float(case["strength"]) if effect is not None else 0.0


def dataset_name(case: dict, with_effect: bool = True) -> str:
    """A folder name that identifies the simulated world without naming its effect (the diagnosis runs blind)."""
    effect, strength = _effective(case, with_effect)
    identity = {
        "shape": case["shape"],
        "effect": effect,
        "strength": strength,
        "seed": int(case["seed"]),
        "velocities": bool(case.get("velocities", True)),
    }
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:12]
    return f"independent-{digest}"


def _complete(folder: Path) -> bool:
    """write_recordings swaps a finished dataset into place: a readable meta.json and its splits mean done."""
    if not (folder / "meta.json").is_file():
        return False
    meta = read_meta(folder)
    return all((folder / path).is_file() for path in meta["splits"].values())


def generate_case(case: dict, out_dir: Path, *, with_effect: bool = True) -> Path:
    """Write the case's dataset (or its null twin) under out_dir and return its folder; reuse it if complete."""
    effect, strength = _effective(case, with_effect)
    name = dataset_name(case, with_effect)
    folder = Path(out_dir) / name
    if _complete(folder):
        return folder
    body = body_model(case["shape"])
    seed = int(case["seed"])
    keep_velocities = bool(case.get("velocities", True))
    splits = {}
    for split_number, (split, count) in enumerate(SPLIT_SIZES.items()):
        tosses = [simulate_toss(body, effect, strength, seed, split_number, toss) for toss in range(count)]
        poses = np.stack([poses for poses, _ in tosses])[:, :, None, :]
        velocities = np.stack([velocities for _, velocities in tosses])[:, :, None, :] if keep_velocities else None
        splits[split] = Split(poses, np.full(count, FRAMES, dtype=np.int64), velocities)
    mesh_path = f"meshes/{body.name}.obj"
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "name": name,
        "dt": DT,
        "gravity": [0.0, 0.0, -GRAVITY],
        "floor_z": 0.0,
        "bodies": [
            {"name": body.name, "mesh": mesh_path, "mass": body.mass, "inertia_diagonal": list(body.inertia_diagonal)}
        ],
        "splits": {split: f"{split}.npz" for split in SPLIT_SIZES},
        "real": False,
        "generator": {"engine": "pybullet", "script": "benchmarks/independent_generator.py"},
    }
    write_recordings(folder, Recordings(meta=meta, meshes={mesh_path: body.mesh}, splits=splits))
    return folder


def size(case: dict, out_dir: Path) -> float:
    """Mean displacement of the body centre by the effect, in object widths, over every frame of every test toss."""
    with_effect = read_recordings(generate_case(case, out_dir), splits=["test"])
    without = read_recordings(generate_case(case, out_dir, with_effect=False), splits=["test"])
    moved = position_error(with_effect.split("test").poses, without.split("test").poses, with_effect.widths())
    return float(moved.mean())


# ---------------------------------------------------------------- proof sets


def _case_line(case: dict) -> str:
    return "  - " + yaml.safe_dump(case, default_flow_style=True, sort_keys=False, width=10_000).strip()


def write_proof_set(path: Path, proof_set: dict) -> None:
    """The proof set as YAML with one flow-style line per case (the layout a reader scans)."""
    header = {key: value for key, value in proof_set.items() if key != "cases"}
    text = yaml.safe_dump(header, sort_keys=False, width=110) + "cases:\n"
    text += "\n".join(_case_line(case) for case in proof_set["cases"]) + "\n"
    path.write_text(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("proof_sets", nargs="+", type=Path, help="proof-set YAML files")
    parser.add_argument("--out", type=Path, default=Path("data/independent"), help="where datasets are written")
    parser.add_argument("--record-sizes", action="store_true", help="write each case's size_widths into its YAML")
    args = parser.parse_args()
    for path in args.proof_sets:
        proof_set = yaml.safe_load(path.read_text())
        for number, case in enumerate(proof_set["cases"]):
            start = time.perf_counter()
            case_size = size(case, args.out)
            print(
                f"{proof_set['set']} case {number:2d} {case['shape']:>20s} {case['effect']!s:>20s} "
                f"strength {case['strength']:<6g} seed {case['seed']}: size {case_size:.3f} widths "
                f"({time.perf_counter() - start:.0f} s) {dataset_name(case)}",
                flush=True,
            )
            case["size_widths"] = round(case_size, 3)
        if args.record_sizes:
            write_proof_set(path, proof_set)


if __name__ == "__main__":
    main()
