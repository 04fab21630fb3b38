"""The ARTICULATED family: an elbow — two bars joined by a hinge — tossed in PyBullet, with or without joint damping.

Each link is a 10.48 × 4 × 4 cm bar of half the benchmark's mass; the hinge's axle runs along the links' y axis 2 cm
beyond each bar's end, so the bars swing freely up to about 90° and then meet: their contact, not a joint limit,
stops the fold (PyBullet collides the two links; every model must too). Angle 0: the bars in one line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactbench import rotations
from contactbench.generation.scenes import SceneSpec
from contactbench.generation.solids import WIDTH, convex_mesh
from contactbench.kinematics import hinge_child, hinge_coordinates, world_vertices
from contactbench.meshes import Mesh
from contactbench.sim.bullet_world import (
    BODY_DYNAMICS_OVERRIDES,
    BulletSettings,
    engine_states,
    forget_contacts,
    table_2a_world,
)
from contactbench.sim.quiet_pybullet import pybullet

THICKNESS = 0.04  # m, each bar's square cross-section
GAP = 0.04  # m between the bars' ends, the axle in its middle
ANGLE_RANGE = 1.2  # rad: initial joint angles are drawn from +-this
RATE_RANGE = 6.0  # rad/s: initial joint rates are drawn from +-this
LOWEST_START = 0.02  # m: an elbow whose lowest corner would start lower is lifted to this height


@dataclass(frozen=True)
class Elbow:
    """The two links' mesh (both alike) and the hinge in their mesh frames (centred at the centre of mass)."""

    link: Mesh
    parent_anchor: np.ndarray
    child_anchor: np.ndarray
    axis: np.ndarray
    damping: float

    @classmethod
    def of(cls, damping: float = 0.0, length: float = WIDTH) -> Elbow:
        half = np.array([length, THICKNESS, THICKNESS]) / 2
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
        reach = length / 2 + GAP / 2
        return cls(
            convex_mesh(corners),
            np.array([reach, 0.0, 0.0]),
            np.array([-reach, 0.0, 0.0]),
            np.array([0.0, 1.0, 0.0]),
            float(damping),
        )

    def joint_entry(self) -> dict:
        """The meta.json 'joints' entry (recordings version 2)."""
        return {
            "name": "elbow",
            "type": "hinge",
            "parent": "link_0",
            "child": "link_1",
            "parent_anchor": self.parent_anchor.tolist(),
            "child_anchor": self.child_anchor.tolist(),
            "axis": self.axis.tolist(),
            "damping": self.damping,
        }


def sample_elbow_state(spec: SceneSpec, elbow: Elbow, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Initial poses [2, 7] and world velocities [2, 6]: the parent as a Table-2 body (random orientation, position and
    horizontal velocity, no spin), a random joint angle and rate; lifted if a corner would start too low."""
    parent = np.concatenate([rng.uniform(spec.position_low, spec.position_high), rotations.uniform_random(rng, 1)[0]])
    parent_velocity = np.concatenate([rng.uniform(spec.velocity_low, spec.velocity_high), np.zeros(3)])
    angle, rate = rng.uniform(-ANGLE_RANGE, ANGLE_RANGE), rng.uniform(-RATE_RANGE, RATE_RANGE)
    child, child_velocity = hinge_child(parent, parent_velocity, elbow, angle, rate)
    poses = np.stack([parent, child])
    lowest = world_vertices(poses, elbow.link.vertices)[..., 2].min()
    poses[:, 2] += max(0.0, LOWEST_START - lowest)
    return poses, np.stack([parent_velocity, child_velocity])


class ElbowScene:
    """A private PyBullet DIRECT world with the floor and one elbow (a two-link multibody), reusable across tosses."""

    def __init__(self, elbow: Elbow, spec: SceneSpec, settings: BulletSettings = BulletSettings()):
        self.elbow = elbow
        self.client = pybullet.connect(pybullet.DIRECT)
        try:
            self._build(spec, settings)
        except BaseException:
            self.close()
            raise

    def _build(self, spec: SceneSpec, settings: BulletSettings) -> None:
        client, elbow = self.client, self.elbow
        table_2a_world(client, settings, settings.gravity)
        floor = pybullet.createMultiBody(
            0.0, pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client), physicsClientId=client
        )
        pybullet.changeDynamics(
            floor,
            -1,
            lateralFriction=settings.floor_friction,
            restitution=settings.floor_restitution,
            physicsClientId=client,
        )
        vertices = elbow.link.vertices.tolist()
        shape = pybullet.createCollisionShape(pybullet.GEOM_MESH, vertices=vertices, physicsClientId=client)
        # A link's shape sits in its link frame, which is the joint's: moved by the offset its centre of mass has too.
        child_shape = pybullet.createCollisionShape(
            pybullet.GEOM_MESH,
            vertices=vertices,
            collisionFramePosition=(-elbow.child_anchor).tolist(),
            physicsClientId=client,
        )
        mass = settings.mass / 2
        _, inertia = elbow.link.mass_properties(mass)
        self.body = pybullet.createMultiBody(
            mass,
            shape,
            linkMasses=[mass],
            linkCollisionShapeIndices=[child_shape],
            linkVisualShapeIndices=[-1],
            linkPositions=[elbow.parent_anchor.tolist()],
            linkOrientations=[[0.0, 0.0, 0.0, 1.0]],
            linkInertialFramePositions=[(-elbow.child_anchor).tolist()],
            linkInertialFrameOrientations=[[0.0, 0.0, 0.0, 1.0]],
            linkParentIndices=[0],
            linkJointTypes=[pybullet.JOINT_REVOLUTE],
            linkJointAxis=[elbow.axis.tolist()],
            # the two bars collide with each other (PyBullet leaves a link and its parent out by default)
            flags=pybullet.URDF_USE_SELF_COLLISION | pybullet.URDF_USE_SELF_COLLISION_INCLUDE_PARENT,
            physicsClientId=client,
        )
        pybullet.setJointMotorControl2(self.body, 0, pybullet.VELOCITY_CONTROL, force=0.0, physicsClientId=client)
        for link in (-1, 0):
            pybullet.changeDynamics(
                self.body,
                link,
                mass=mass,
                localInertiaDiagonal=np.diag(inertia).tolist(),
                lateralFriction=spec.friction,
                restitution=spec.restitution,
                physicsClientId=client,
                **BODY_DYNAMICS_OVERRIDES,
            )

    def close(self) -> None:
        if self.client >= 0:
            pybullet.disconnect(physicsClientId=self.client)
            self.client = -1

    def toss(
        self, poses: np.ndarray, velocities: np.ndarray, frames: int, *, record_contacts: bool = False
    ) -> tuple[np.ndarray, None]:
        """States [frames, 2, 13] (position, quaternion x y z w, linear and angular velocity; world frame) of the two
        links from poses [2, 7] and velocities [2, 6] (the child's must follow the hinge)."""
        if record_contacts:
            raise ValueError("contact forces are not recorded for articulated bodies")
        client, body = self.client, self.body
        forget_contacts(client, (body,))
        angle, rate = hinge_coordinates(poses[0], velocities[0], poses[1], velocities[1], self.elbow)
        pybullet.resetBasePositionAndOrientation(
            body, poses[0, :3].tolist(), rotations.wxyz_to_xyzw(poses[0, 3:]).tolist(), physicsClientId=client
        )
        pybullet.resetBaseVelocity(body, velocities[0, :3].tolist(), velocities[0, 3:].tolist(), physicsClientId=client)
        pybullet.resetJointState(body, 0, float(angle), float(rate), physicsClientId=client)
        readings = []
        for t in range(frames):
            if t:
                if self.elbow.damping:  # changeDynamics' jointDamping does nothing to this multibody: applied here
                    rate = pybullet.getJointState(body, 0, physicsClientId=client)[1]
                    pybullet.setJointMotorControl2(
                        body, 0, pybullet.TORQUE_CONTROL, force=-self.elbow.damping * rate, physicsClientId=client
                    )
                pybullet.stepSimulation(physicsClientId=client)
            readings.append(pybullet.getBasePositionAndOrientation(body, client))
            readings.append(pybullet.getBaseVelocity(body, client))
            link = pybullet.getLinkState(
                body, 0, computeLinkVelocity=1, computeForwardKinematics=1, physicsClientId=client
            )
            readings.append((link[0], link[1]))
            readings.append((link[6], link[7]))
        return engine_states(readings, frames, 2), None
