"""The one PyBullet world of the benchmark, Table 2a: its settings and the pieces every PyBullet world here is built
from, the generator's (generation/bullet.py, generation/articulated.py) and the identifiable engine's
(bullet_engine.py) alike, so that a fitted world is the world that made the data."""

from __future__ import annotations

import itertools
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np

from contactbench import rotations
from contactbench.meshes import Mesh, obj_text
from contactbench.scene import Static
from contactbench.sim.quiet_pybullet import pybullet
from contactbench.values import set_floats, set_vectors

# Bodies wait here between tosses: far above the floor and 10 m from each other, beyond any contact threshold.
_PARKING_SPACING = 10.0
_PARKING_HEIGHT = 10.0
_IDENTITY_XYZW = (0.0, 0.0, 0.0, 1.0)
ENGINE_STATE_SIZE = 13  # per body and frame: position, quaternion x y z w, linear velocity, angular velocity
_flatten = itertools.chain.from_iterable
# PyBullet defaults replaced on purpose for every object: 0.04 linear and angular air drag nobody asked for, and
# a 1 mm collision margin that would keep every object hovering 1 mm above the floor. (The AABB-box inertia
# default is replaced too, by the mesh's own, where a world builds its bodies.)
BODY_DYNAMICS_OVERRIDES = MappingProxyType(
    {
        "rollingFriction": 0.0,
        "spinningFriction": 0.0,
        "linearDamping": 0.0,
        "angularDamping": 0.0,
        "collisionMargin": 0.0,
    }
)


@dataclass(frozen=True)
class BulletSettings:
    """Engine settings shared by every variant (Table 2a) and the common object properties (Section 3)."""

    dt: float = 0.00676  # s per frame; one engine step per frame
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
    restitution_velocity_threshold: float = 0.0
    floor_friction: float = 1.0
    floor_restitution: float = 1.0
    mass: float = 0.37  # kg, every object
    width: float = 0.1048  # m, largest axis-aligned bounding-box extent of every object
    frames: int = 140  # recorded frames per toss, frame 0 being the initial state

    def __post_init__(self) -> None:
        set_floats(self, "dt", "restitution_velocity_threshold", "floor_friction", "floor_restitution", "mass", "width")
        set_vectors(self, "gravity")
        object.__setattr__(self, "frames", int(self.frames))


def table_2a_world(client: int, settings: BulletSettings, gravity: np.ndarray) -> None:
    """Table 2a's engine settings: one engine step per frame, restitution at any impact speed, deterministic pair
    order; and gravity."""
    pybullet.setPhysicsEngineParameter(
        fixedTimeStep=settings.dt,
        numSubSteps=0,
        restitutionVelocityThreshold=settings.restitution_velocity_threshold,
        deterministicOverlappingPairs=1,
        physicsClientId=client,
    )
    pybullet.setGravity(*np.asarray(gravity, dtype=float).tolist(), physicsClientId=client)


def convex_compound(client: int, pieces: Sequence[Mesh], origin: np.ndarray | None = None) -> int:
    """A collision shape of convex pieces: one hull (PyBullet wraps vertices without indices in their hull), or, for
    several, an OBJ with one object per piece, which PyBullet loads as a compound of their hulls. `origin`: where the
    pieces' frame sits in the frame the shape is attached to (a multibody link's frame is its joint's)."""
    placed = {} if origin is None else {"collisionFramePosition": np.asarray(origin, dtype=float).tolist()}
    if len(pieces) == 1:
        return pybullet.createCollisionShape(
            pybullet.GEOM_MESH, vertices=pieces[0].vertices.tolist(), physicsClientId=client, **placed
        )
    with tempfile.TemporaryDirectory(prefix="contactbench-pieces-") as folder:
        path = Path(folder) / "pieces.obj"
        lines, offset = [], 0
        for i, piece in enumerate(pieces):  # OBJ indices count across objects
            lines.append(f"o piece_{i}\n" + obj_text(Mesh(piece.vertices, piece.faces + offset)))
            offset += len(piece.vertices)
        path.write_text("".join(lines))
        return pybullet.createCollisionShape(pybullet.GEOM_MESH, fileName=str(path), physicsClientId=client, **placed)


def change_dynamics(client: int, body: int, link: int, **settings) -> None:
    """pybullet.changeDynamics of a body's base (link -1) or link. For a link, one setting a call: several in one call
    went partly to the base or were dropped (a collision margin beside them dropped the mass, inertia and material;
    air drag beside them sent the inertia to the base), so each goes alone, the mass before the inertia it resets."""
    if link < 0:
        pybullet.changeDynamics(body, link, physicsClientId=client, **settings)
        return
    compliance = {key: settings.pop(key) for key in ("contactStiffness", "contactDamping") if key in settings}
    order = sorted(settings, key=lambda key: key == "localInertiaDiagonal")
    for update in [{key: settings[key]} for key in order] + ([compliance] if compliance else []):
        pybullet.changeDynamics(body, link, physicsClientId=client, **update)


def add_static(
    client: int, static: Sequence[tuple[Static, Mesh | None]], friction: float, restitution: float
) -> tuple[int, ...]:
    """Static bodies (mass 0) for terrain entries, with the floor's material: convex meshes as their hulls, height
    fields as concave triangle meshes."""
    bodies = []
    for entry, mesh in static:
        if entry.heightfield is not None:
            surface = entry.heightfield.surface()
            shape = pybullet.createCollisionShape(
                pybullet.GEOM_MESH,
                vertices=surface.vertices.tolist(),
                indices=surface.faces.ravel().tolist(),
                flags=pybullet.GEOM_FORCE_CONCAVE_TRIMESH,
                physicsClientId=client,
            )
        else:
            shape = convex_compound(client, [mesh])
        body = pybullet.createMultiBody(
            0.0,
            shape,
            basePosition=entry.pose[:3].tolist(),
            baseOrientation=rotations.wxyz_to_xyzw(entry.pose[3:]).tolist(),
            physicsClientId=client,
        )
        pybullet.changeDynamics(
            body,
            -1,
            lateralFriction=friction,
            restitution=restitution,
            rollingFriction=0.0,
            spinningFriction=0.0,
            collisionMargin=0.0,
            physicsClientId=client,
        )
        bodies.append(body)
    return tuple(bodies)


def parking_spot(k: int) -> tuple[float, float, float]:
    """Where body k waits between tosses: far above the floor and away from every other body."""
    return (_PARKING_SPACING * (k + 1), 0.0, _PARKING_HEIGHT)


def forget_contacts(client: int, bodies: tuple[int, ...]) -> None:
    """Contact manifolds survive a teleport and warm-start the next solve, so a toss would depend on the one before
    it: parking every body far apart and running collision detection once empties all manifolds."""
    for k, body in enumerate(bodies):
        pybullet.resetBasePositionAndOrientation(body, parking_spot(k), _IDENTITY_XYZW, physicsClientId=client)
    pybullet.performCollisionDetection(physicsClientId=client)


def engine_states(readings: list[tuple], frames: int, count: int) -> np.ndarray:
    """States [frames, count, 13] from PyBullet's (pose, velocity) reading tuples, body by body and frame by frame, in
    one conversion (converting each reading in the stepping loop cost as much as the reads)."""
    flat = np.fromiter(_flatten(_flatten(readings)), dtype=np.float64, count=frames * count * ENGINE_STATE_SIZE)
    return flat.reshape(frames, count, ENGINE_STATE_SIZE)


def recorded_motion(engine_states: np.ndarray, initial_orientations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses [..., T, K, 7] (w-first) and velocities [..., T, K, 6] from PyBullet's states [..., T, K, 13]
    (position, quaternion x y z w, linear velocity, angular velocity; world frame), over any leading axes.

    Bullet hands back either sign of a quaternion from one step to the next; the signs are chosen to make each
    body's quaternion path continuous, starting on the side of `initial_orientations` [..., K, 4] (w-first).
    """
    quaternions = rotations.xyzw_to_wxyz(engine_states[..., 3:7])
    initial = np.asarray(initial_orientations, dtype=np.float64)[..., None, :, :]
    previous = np.concatenate([initial, quaternions[..., :-1, :, :]], axis=-3)
    steps = np.where(np.einsum("...q,...q->...", quaternions, previous) < 0, -1.0, 1.0)
    quaternions *= np.cumprod(steps, axis=-2)[..., None]
    return np.concatenate([engine_states[..., :3], quaternions], axis=-1), np.ascontiguousarray(engine_states[..., 7:])
