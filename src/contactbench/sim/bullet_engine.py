"""PyBullet as an identifiable engine: contact parameters, a world of any recordings scene, URDF of the fitted scene.

Conventions
-----------
* The world is the generator's (generation/bullet.py, Table 2a): one engine step per frame (dt / substeps with
  substeps), no sub-stepping, restitution at any impact speed (threshold 0), deterministic pair order, and the
  bodies without PyBullet's default air drag and 1 mm collision margin (`BODY_DYNAMICS_OVERRIDES`). PyBullet combines
  two materials by multiplying their friction and their restitution; the floor carries 1 for both, so a body's own
  coefficients are the pair's. Bodies collide as their convex pieces (their meshes' hulls where they have none), with
  one another, the floor and the terrain (recordings version 2; the floor's material). Joints are not built here.
* PyBullet places and reports a body by its inertial frame (centre of mass, principal axes); recordings poses are the
  mesh frame's. A world converts at this boundary (`_to_inertial`, `_to_mesh`).

Parameters (`BulletParameters`)
-------------------------------
object_friction, restitution: per body (lateral Coulomb friction; Newton restitution of normal velocity).
spinning_friction (m): torsional friction, a torque of spinning_friction x the normal force opposing spin about the
normal; rolling_friction (m): the same against rolling. contact_stiffness (N/m) and contact_damping (N s/m): a
compliant contact (PyBullet turns them into each step's ERP = h k / (h k + d) and CFM = 1 / (h k + d)); None (both)
keeps PyBullet's own rigid contact, which resolves penetration by error reduction (what the generator uses).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import numpy as np
import pybullet

from contactbench import rotations
from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.generation.bullet import (
    BODY_DYNAMICS_OVERRIDES,
    add_static,
    convex_compound,
    engine_states,
    forget_contacts,
    parking_spot,
    recorded_motion,
)
from contactbench.generation.scenes import BulletSettings
from contactbench.meshes import obj_text
from contactbench.recordings import Scene
from contactbench.sim.engines import Dimension, Engine
from contactbench.sim.stepped import SteppedRollouts, World
from contactbench.values import freeze_numbers

TABLE_2A = BulletSettings()
CONTACT_MODES = (
    "rigid",
    "compliant",
)  # the generator's engine settings: restitution threshold, floor friction and restitution


@dataclass(frozen=True)
class BulletParameters:
    """PyBullet contact parameters of a scene (see the module docstring)."""

    object_friction: tuple[float, ...]
    restitution: tuple[float, ...]
    spinning_friction: float = 0.0
    rolling_friction: float = 0.0
    contact_stiffness: float | None = None
    contact_damping: float | None = None

    def __post_init__(self):
        freeze_numbers(self, vectors=("object_friction", "restitution"))
        if len(self.object_friction) != len(self.restitution):
            raise ContactbenchError(
                f"{len(self.object_friction)} frictions and {len(self.restitution)} restitutions "
                "(expected one per body)"
            )
        coefficients = self.object_friction + (self.spinning_friction, self.rolling_friction)
        if not all(np.isfinite(coefficients)) or min(coefficients) < 0:
            raise ContactbenchError(f"PyBullet friction coefficients must be finite and >= 0, got {self}")
        if not all(0 <= r <= 1 for r in self.restitution):
            raise ContactbenchError(f"PyBullet restitution must lie in [0, 1], got {self.restitution}")
        if (self.contact_stiffness is None) != (self.contact_damping is None):
            raise ContactbenchError("PyBullet contact_stiffness and contact_damping are given together or not at all")
        if self.contact_stiffness is not None and not (
            np.isfinite(self.contact_stiffness) and self.contact_stiffness > 0 and 0 <= self.contact_damping < np.inf
        ):
            raise ContactbenchError(
                f"PyBullet contact stiffness must be > 0 and damping >= 0, finite, got {self.contact_stiffness}, "
                f"{self.contact_damping}"
            )


def inertial_frames(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per body: centre of mass [K, 3] and principal axes [K, 4] (w-first) in the mesh frame, principal moments [K, 3].

    Within 1e-9 of the origin and of diagonal (a generated scene's mesh frame) they are taken as exactly so, so that a
    generated dataset's world is the generator's to the last bit."""
    coms, axes, moments = [], [], []
    for k in range(scene.n_bodies):
        com, inertia = scene.inertial(k)
        width = scene.body_mesh(k).width
        com = np.where(np.abs(com) > 1e-9 * width, com, 0.0)
        if np.abs(inertia - np.diag(np.diag(inertia))).max() <= 1e-9 * np.trace(inertia):
            principal, rotation = np.diag(inertia).copy(), np.eye(3)
        else:
            principal, rotation = np.linalg.eigh(inertia)
            rotation[:, 2] *= np.linalg.det(rotation)  # a proper rotation
        coms.append(com)
        axes.append(rotations.from_matrix(rotation))
        moments.append(principal)
    return np.array(coms), np.array(axes), np.array(moments)


class BulletWorld(World):
    """A private PyBullet DIRECT world of a recordings scene, reused toss after toss."""

    def __init__(self, scene: Scene, substeps: int = 1):
        self.scene = scene
        self.substeps = int(substeps)
        self.coms, self.axes, self.moments = inertial_frames(scene)
        # Every mesh frame at its centre of mass and along its principal axes (a generated scene): nothing to convert
        self.mesh_frames_inertial = not self.coms.any() and bool(np.all(self.axes == [1.0, 0.0, 0.0, 0.0]))
        self.parameters: BulletParameters | None = None
        self.client = pybullet.connect(pybullet.DIRECT)
        try:
            self.bodies = self._build()
        except BaseException:
            self.close()
            raise

    def _build(self) -> tuple[int, ...]:
        scene, client = self.scene, self.client
        # One stepSimulation per frame: PyBullet's own sub-stepping splits it into `substeps` steps of dt / substeps
        # (a Python loop of them cost a tenth of the stepping); none for one, as the generator steps.
        pybullet.setPhysicsEngineParameter(
            fixedTimeStep=scene.dt,
            numSubSteps=self.substeps if self.substeps > 1 else 0,
            restitutionVelocityThreshold=TABLE_2A.restitution_velocity_threshold,
            deterministicOverlappingPairs=1,
            physicsClientId=client,
        )
        pybullet.setGravity(*scene.gravity.tolist(), physicsClientId=client)
        floor_shape = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client)
        self.floor = pybullet.createMultiBody(
            0.0, floor_shape, basePosition=(0.0, 0.0, scene.floor_z), physicsClientId=client
        )
        pybullet.changeDynamics(
            self.floor,
            -1,
            lateralFriction=TABLE_2A.floor_friction,
            restitution=TABLE_2A.floor_restitution,
            rollingFriction=0.0,
            spinningFriction=0.0,
            physicsClientId=client,
        )
        shapes: dict[str, int] = {}
        bodies = []
        for k, body in enumerate(scene.bodies):
            if body.mesh not in shapes:  # a body's convex pieces (its hull, where it has none), in its mesh frame
                shapes[body.mesh] = convex_compound(client, scene.body_pieces(k))
            handle = pybullet.createMultiBody(
                body.mass,
                shapes[body.mesh],
                basePosition=parking_spot(k),
                baseInertialFramePosition=self.coms[k].tolist(),
                baseInertialFrameOrientation=rotations.wxyz_to_xyzw(self.axes[k]).tolist(),
                physicsClientId=client,
            )
            pybullet.changeDynamics(
                handle,
                -1,
                mass=body.mass,
                localInertiaDiagonal=self.moments[k].tolist(),
                physicsClientId=client,
                **BODY_DYNAMICS_OVERRIDES,
            )
            bodies.append(handle)
        # terrain after the bodies, as the generator builds it: PyBullet's contact order follows creation order
        add_static(
            client,
            [(entry, scene.meshes.get(entry.mesh)) for entry in scene.static],
            TABLE_2A.floor_friction,
            TABLE_2A.floor_restitution,
        )
        return tuple(bodies)

    def _apply(self, parameters: BulletParameters) -> None:
        if len(parameters.object_friction) != len(self.bodies):
            raise ContactbenchError(
                f"{len(parameters.object_friction)} object frictions for a scene of {len(self.bodies)} bodies"
            )
        if parameters == self.parameters:
            return
        compliance = {}
        if parameters.contact_stiffness is not None:
            compliance = {
                "contactStiffness": parameters.contact_stiffness,
                "contactDamping": parameters.contact_damping,
            }
        elif self.parameters is not None and self.parameters.contact_stiffness is not None:
            # PyBullet has no way back to its rigid contact for a body: a world of the scene starts afresh.
            self.close()
            self.client = pybullet.connect(pybullet.DIRECT)
            self.bodies = self._build()
        for k, handle in enumerate(self.bodies):
            pybullet.changeDynamics(
                handle,
                -1,
                lateralFriction=parameters.object_friction[k],
                restitution=parameters.restitution[k],
                spinningFriction=parameters.spinning_friction,
                rollingFriction=parameters.rolling_friction,
                physicsClientId=self.client,
                **compliance,
            )
        self.parameters = parameters

    def _to_inertial(self, poses: np.ndarray, velocities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mesh-frame poses [K, 7] / world velocities [K, 6] -> the inertial frames' (PyBullet's base frames)."""
        offset = rotations.rotate(poses[:, 3:], self.coms)
        orientation = rotations.multiply(poses[:, 3:], self.axes)
        linear = velocities[:, :3] + np.cross(velocities[:, 3:], offset)
        return np.concatenate([poses[:, :3] + offset, orientation], axis=1), np.concatenate(
            [linear, velocities[:, 3:]], axis=1
        )

    def _to_mesh(self, poses: np.ndarray, velocities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of _to_inertial, over leading axes: poses [..., K, 7], velocities [..., K, 6]."""
        orientation = rotations.multiply(poses[..., 3:], rotations.conjugate(self.axes))
        offset = rotations.rotate(orientation, np.broadcast_to(self.coms, poses.shape[:-1] + (3,)))
        linear = velocities[..., :3] - np.cross(velocities[..., 3:], offset)
        return np.concatenate([poses[..., :3] - offset, orientation], axis=-1), np.concatenate(
            [linear, velocities[..., 3:]], axis=-1
        )

    def toss(
        self, parameters: BulletParameters, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int
    ) -> tuple[np.ndarray, np.ndarray]:
        self._apply(parameters)
        client, bodies = self.client, self.bodies
        forget_contacts(client, bodies)
        base_poses, base_velocities = np.asarray(poses0), np.asarray(velocities0)
        if not self.mesh_frames_inertial:
            base_poses, base_velocities = self._to_inertial(base_poses, base_velocities)
        for body, pose, velocity in zip(bodies, base_poses, base_velocities):
            pybullet.resetBasePositionAndOrientation(
                body, pose[:3].tolist(), rotations.wxyz_to_xyzw(pose[3:]).tolist(), physicsClientId=client
            )
            pybullet.resetBaseVelocity(body, velocity[:3].tolist(), velocity[3:].tolist(), physicsClientId=client)
        step, read_pose, read_velocity = (
            pybullet.stepSimulation,
            pybullet.getBasePositionAndOrientation,
            pybullet.getBaseVelocity,
        )
        readings = []
        record = readings.append
        for _ in range(n_steps):
            step(client)
            for body in bodies:
                record(read_pose(body, client))
                record(read_velocity(body, client))
        states = engine_states(readings, n_steps, len(bodies))
        poses, velocities = recorded_motion(states, base_poses[:, 3:])
        return (poses, velocities) if self.mesh_frames_inertial else self._to_mesh(poses, velocities)

    def close(self) -> None:
        if self.client >= 0:
            pybullet.disconnect(physicsClientId=self.client)
            self.client = -1


class BulletEngine(Engine):
    """PyBullet 3 (Bullet's sequential-impulse solver), the engine that generated the synthetic datasets."""

    name = "bullet"

    def check_scene(self, scene: Scene) -> None:
        if scene.joints:
            raise NotApplicable(
                f"the PyBullet engine here simulates free bodies (convex pieces, on any terrain); {scene.name} has "
                "joints (model=sysid and mujoco_default simulate those)"
            )

    def default_parameters(self, n_bodies: int) -> BulletParameters:
        """PyBullet's own body defaults: friction 0.5, restitution 0, no spinning or rolling friction, rigid contact."""
        return BulletParameters(object_friction=(0.5,) * n_bodies, restitution=(0.0,) * n_bodies)

    def dimensions(self, n_bodies: int) -> tuple[Dimension, ...]:
        per_body = [Dimension(f"object_friction_{k}", 0.0, 1.0) for k in range(n_bodies)]
        per_body += [Dimension(f"restitution_{k}", 0.0, 1.0, init=0.2) for k in range(n_bodies)]
        return (
            *per_body,
            # Log scales from "none to speak of" up: 1e-6 m of both moved the frictioncubes' tosses by 0.0008 widths
            # (1e-5 m: by 0.005), where the generator has none.
            Dimension("spinning_friction", 1e-6, 1e-2, log=True, init=1e-4),
            Dimension("rolling_friction", 1e-6, 1e-2, log=True, init=1e-4),
            # PyBullet's rigid contact (error reduction with split impulses) is not a limit of its compliant one: at
            # 1e9 N/m the compliant contact still moved the frictioncubes' tosses 0.06 widths off the rigid ones.
            Dimension("contact", choices=CONTACT_MODES),
            Dimension("contact_stiffness", 1e3, 1e8, log=True, init=1e5, when=("contact", "compliant")),
            # Damping relative to stiffness x the Table 2a step: ERP = 1 / (1 + ratio) at that step.
            Dimension("contact_damping_ratio", 0.0, 10.0, init=4.0, when=("contact", "compliant")),
        )

    def from_values(self, values: Mapping[str, float], n_bodies: int) -> BulletParameters:
        compliant = CONTACT_MODES[int(round(values["contact"]))] == "compliant"
        stiffness = float(values["contact_stiffness"])
        return BulletParameters(
            object_friction=tuple(float(values[f"object_friction_{k}"]) for k in range(n_bodies)),
            restitution=tuple(float(values[f"restitution_{k}"]) for k in range(n_bodies)),
            spinning_friction=float(values["spinning_friction"]),
            rolling_friction=float(values["rolling_friction"]),
            contact_stiffness=stiffness if compliant else None,
            contact_damping=float(values["contact_damping_ratio"]) * stiffness * TABLE_2A.dt if compliant else None,
        )

    def to_values(self, parameters: BulletParameters) -> dict[str, float]:
        values = {f"object_friction_{k}": f for k, f in enumerate(parameters.object_friction)}
        values |= {f"restitution_{k}": r for k, r in enumerate(parameters.restitution)}
        values |= {"spinning_friction": parameters.spinning_friction, "rolling_friction": parameters.rolling_friction}
        if parameters.contact_stiffness is None:  # rigid: the compliant entries do not act, at their search start
            unused = {d.name: d.init for d in self.dimensions(0) if d.when == ("contact", "compliant")}
            return values | {"contact": 0.0} | unused
        ratio = parameters.contact_damping / (parameters.contact_stiffness * TABLE_2A.dt)
        return values | {
            "contact": 1.0,
            "contact_stiffness": parameters.contact_stiffness,
            "contact_damping_ratio": ratio,
        }

    def rollouts(self, scene: Scene, nthread: int | None = None, substeps: int = 1) -> SteppedRollouts:
        return SteppedRollouts(scene, BulletWorld, nthread, substeps)

    def scene_files(self, scene: Scene, parameters: BulletParameters, substeps: int = 1) -> dict[str, str]:
        return scene_files(scene, parameters)


def _numbers(values) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(values))


def _roll_pitch_yaw(q: np.ndarray) -> np.ndarray:
    """URDF's rpy of a rotation (w-first quaternion): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    m = rotations.to_matrix(q)
    return np.array([np.arctan2(m[2, 1], m[2, 2]), -np.arcsin(np.clip(m[2, 0], -1, 1)), np.arctan2(m[1, 0], m[0, 0])])


def scene_files(scene: Scene, parameters: BulletParameters) -> dict[str, str]:
    """One URDF per body (body_<k>.urdf: pybullet.loadURDF with flags=URDF_USE_INERTIA_FROM_FILE, else PyBullet
    computes an inertia of its own from the collision shape) with its inertial frame, its convex pieces
    (meshes/body_<k>_<i>.obj, one <collision> each; a convex body has one) and its contact parameters in PyBullet's
    <contact> extension; terrain as static_<i>.urdf (mass 0; a height field as its triangle surface); the world
    settings (step, gravity, the floor and its material) are stated in a comment, as the generator sets them."""
    coms, axes, moments = inertial_frames(scene)
    world = (
        f"PyBullet world: fixedTimeStep {scene.dt!r} s, gravity {_numbers(scene.gravity)}, a plane at z = "
        f"{scene.floor_z!r} with lateral friction {TABLE_2A.floor_friction!r} and restitution "
        f"{TABLE_2A.floor_restitution!r} (PyBullet multiplies the two materials' coefficients), "
        f"restitutionVelocityThreshold {TABLE_2A.restitution_velocity_threshold!r}, numSubSteps 0; load with "
        "flags=URDF_USE_INERTIA_FROM_FILE; after loading: "
        + ", ".join(f"{key} {value!r}" for key, value in BODY_DYNAMICS_OVERRIDES.items() if key != "collisionMargin")
    )
    files = {}
    for k, body in enumerate(scene.bodies):
        compliance = ""
        if parameters.contact_stiffness is not None:
            stiffness, damping = parameters.contact_stiffness, parameters.contact_damping
            compliance = f'<stiffness value="{stiffness!r}"/><damping value="{damping!r}"/>'
        files[f"body_{k}.urdf"] = "\n".join(
            [
                "<?xml version='1.0'?>",
                f"<!-- {world} -->",
                f"<robot name={quoteattr(body.name)}>",
                f"<link name={quoteattr(body.name)}>",
                f'<contact><lateral_friction value="{parameters.object_friction[k]!r}"/>'
                f'<restitution value="{parameters.restitution[k]!r}"/>'
                f'<spinning_friction value="{parameters.spinning_friction!r}"/>'
                f'<rolling_friction value="{parameters.rolling_friction!r}"/>{compliance}</contact>',
                f'<inertial><origin xyz="{_numbers(coms[k])}" rpy="{_numbers(_roll_pitch_yaw(axes[k]))}"/>'
                f'<mass value="{body.mass!r}"/><inertia ixx="{float(moments[k][0])!r}" ixy="0" ixz="0" '
                f'iyy="{float(moments[k][1])!r}" iyz="0" izz="{float(moments[k][2])!r}"/></inertial>',
                *(
                    f'<collision><geometry><mesh filename="meshes/body_{k}_{i}.obj"/></geometry></collision>'
                    for i in range(len(scene.body_pieces(k)))
                ),
                f'<visual><geometry><mesh filename="meshes/body_{k}.obj"/></geometry></visual>',
                "</link>",
                "</robot>",
            ]
        )
    for k in range(scene.n_bodies):
        files[f"meshes/body_{k}.obj"] = obj_text(scene.body_mesh(k))
        for i, piece in enumerate(scene.body_pieces(k)):
            files[f"meshes/body_{k}_{i}.obj"] = obj_text(piece)
    for i, entry in enumerate(scene.static):
        surface = entry.heightfield.surface() if entry.heightfield is not None else scene.meshes[entry.mesh]
        files[f"meshes/static_{i}.obj"] = obj_text(surface)
        files[f"static_{i}.urdf"] = "\n".join(
            [
                "<?xml version='1.0'?>",
                f"<!-- terrain, fixed (useFixedBase=True), the floor's material; {world} -->",
                f"<robot name={quoteattr(entry.name)}>",
                f"<link name={quoteattr(entry.name)}>",
                f'<contact><lateral_friction value="{TABLE_2A.floor_friction!r}"/>'
                f'<restitution value="{TABLE_2A.floor_restitution!r}"/></contact>',
                '<inertial><mass value="0"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial>',
                f'<collision><origin xyz="{_numbers(entry.pose[:3])}" '
                f'rpy="{_numbers(_roll_pitch_yaw(entry.pose[3:]))}"/>'
                f'<geometry><mesh filename="meshes/static_{i}.obj"/></geometry></collision>',
                "</link>",
                "</robot>",
            ]
        )
    return files
