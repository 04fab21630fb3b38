"""A recordings scene in one private PyBullet DIRECT world (BulletWorld), built once and tossed again and again under
any candidate parameters: the world the PyBullet engine (bullet_engine.py) rolls out.

Conventions
-----------
* The world is the generator's (sim/bullet_world.py, Table 2a): one engine step per frame (dt / substeps with
  substeps), no sub-stepping, restitution at any impact speed (threshold 0), deterministic pair order, and the
  bodies without PyBullet's default air drag and 1 mm collision margin (`BODY_DYNAMICS_OVERRIDES`). PyBullet combines
  two materials by multiplying their friction and their restitution; the floor carries 1 for both, so a body's own
  coefficients are the pair's. Bodies collide as their convex pieces (their meshes' hulls where they have none), with
  one another, the floor and the terrain (recordings version 2; the floor's material).
* Hinges (recordings version 2) as the generator builds its elbow (generation/articulated.py): one multibody per tree
  of jointed bodies, its root the base, every other body a link on a revolute joint whose frame sits at the anchor
  (link frames parallel to the mesh frames), its links colliding with one another, parent and child included.
  Joint damping is a torque against the joint rate applied before each step (PyBullet's own jointDamping does not
  act on such a multibody), Coulomb friction a velocity motor held at 0 with the friction as its largest torque
  (PyBullet's default motor switched off where there is none), a range PyBullet's joint limit. A toss starts from the
  roots' poses and velocities and the joint angles and rates (`kinematics.hinge_coordinates`) and returns every
  child from its parent and its joint's state (`kinematics.hinge_child`), so the output keeps each hinge exactly.
* PyBullet places and reports a body by its inertial frame (centre of mass, principal axes); recordings poses are the
  mesh frame's. A world converts at this boundary (`_to_inertial`, `_to_mesh`).
"""

from __future__ import annotations

import numpy as np

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.kinematics import hinge_child, hinge_coordinates
from contactbench.scene import Joint, Scene
from contactbench.sim.articulation import articulated
from contactbench.sim.bullet_scene import TABLE_2A, BulletParameters, link_origins, trees
from contactbench.sim.bullet_world import (
    BODY_DYNAMICS_OVERRIDES,
    add_static,
    change_dynamics,
    convex_compound,
    engine_states,
    forget_contacts,
    parking_spot,
    recorded_motion,
)
from contactbench.sim.effects import NO_EFFECTS, InertiaBoxDrag, SceneEffects, inertial_frames
from contactbench.sim.quiet_pybullet import pybullet
from contactbench.sim.stepped import World


def _start_angle(joint: Joint, angle: float) -> float:
    """The turn nearest the middle of the joint's range (hinge_coordinates gives one in (-pi, pi])."""
    if joint.range is None:
        return float(angle)
    middle = 0.5 * (joint.range[0] + joint.range[1])
    return float(angle + 2 * np.pi * np.round((middle - angle) / (2 * np.pi)))


class BulletWorld(World):
    """A private PyBullet DIRECT world of a recordings scene, reused toss after toss."""

    def __init__(self, scene: Scene, substeps: int = 1):
        self.scene = scene
        self.substeps = int(substeps)
        self._inertial(NO_EFFECTS)
        self.joints = scene.joints
        self.trees = trees(scene)
        self.roots = np.array([tree.root for tree in self.trees])
        self.origins = link_origins(scene)
        # Per body: its tree and its link there (-1: the base)
        self.links = [(0, -1)] * scene.n_bodies
        for i, tree in enumerate(self.trees):
            self.links[tree.root] = (i, -1)
            for n, j in enumerate(tree.joints):
                self.links[self.joints[j].child] = (i, n)
        self.parameters: BulletParameters | None = None
        self.drag: InertiaBoxDrag | None = None  # None without a fluid
        self.client = pybullet.connect(pybullet.DIRECT)
        try:
            self.bodies = self._build()
        except BaseException:
            self.close()
            raise

    def _inertial(self, effects: SceneEffects) -> None:
        """The bodies' inertial frames with `effects`' centre of mass and inertia (the world is then built anew)."""
        self.inertial_effects = (effects.com_offset, effects.inertia_scale)
        self.coms, self.axes, self.moments = inertial_frames(self.scene, effects)
        # Every mesh frame at its centre of mass and along its principal axes (a generated scene): nothing to convert
        self.mesh_frames_inertial = not self.coms.any() and bool(np.all(self.axes == [1.0, 0.0, 0.0, 0.0]))

    def close(self) -> None:
        if pybullet.isConnected(self.client):
            pybullet.disconnect(self.client)

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
        shapes: dict[tuple, int] = {}

        def shape(k: int) -> int:
            """Body k's convex pieces (its hull, where it has none), in its link frame."""
            origin = -self.origins[k]
            key = (scene.bodies[k].mesh, *origin.tolist())
            if key not in shapes:
                shapes[key] = convex_compound(client, scene.body_pieces(k), origin if origin.any() else None)
            return shapes[key]

        bodies = []
        for i, tree in enumerate(self.trees):
            k, joints = tree.root, [self.joints[j] for j in tree.joints]
            link_of = {joint.child: n for n, joint in enumerate(joints)}
            children = [joint.child for joint in joints]
            hinges = {}
            if joints:
                hinges = {
                    "linkMasses": [scene.bodies[c].mass for c in children],
                    "linkCollisionShapeIndices": [shape(c) for c in children],
                    "linkVisualShapeIndices": [-1] * len(joints),
                    "linkPositions": [(joint.parent_anchor - self.origins[joint.parent]).tolist() for joint in joints],
                    "linkOrientations": [[0.0, 0.0, 0.0, 1.0]] * len(joints),  # angle 0: parallel frames
                    "linkInertialFramePositions": [(self.coms[c] - self.origins[c]).tolist() for c in children],
                    "linkInertialFrameOrientations": [rotations.wxyz_to_xyzw(self.axes[c]).tolist() for c in children],
                    "linkParentIndices": [link_of.get(joint.parent, -1) + 1 for joint in joints],  # 0: the base
                    "linkJointTypes": [pybullet.JOINT_REVOLUTE] * len(joints),
                    "linkJointAxis": [joint.axis.tolist() for joint in joints],
                    # jointed bodies collide with each other (PyBullet leaves a link and its parent out by default)
                    "flags": pybullet.URDF_USE_SELF_COLLISION | pybullet.URDF_USE_SELF_COLLISION_INCLUDE_PARENT,
                }
            handle = pybullet.createMultiBody(
                scene.bodies[k].mass,
                shape(k),
                basePosition=parking_spot(i),
                baseInertialFramePosition=self.coms[k].tolist(),
                baseInertialFrameOrientation=rotations.wxyz_to_xyzw(self.axes[k]).tolist(),
                physicsClientId=client,
                **hinges,
            )
            for body, link in ((k, -1), *((c, n) for n, c in enumerate(children))):
                change_dynamics(
                    client,
                    handle,
                    link,
                    mass=scene.bodies[body].mass,
                    localInertiaDiagonal=self.moments[body].tolist(),
                    **BODY_DYNAMICS_OVERRIDES,
                )
            for n, joint in enumerate(joints):
                if joint.range is not None:  # a limit, once set, stays: ranges are the scene's, never a candidate's
                    pybullet.changeDynamics(
                        handle,
                        n,
                        jointLowerLimit=joint.range[0],
                        jointUpperLimit=joint.range[1],
                        physicsClientId=client,
                    )
            bodies.append(handle)
        self.inertia_factor = 1.0  # the inertia scale applied, relative to the scene's
        # terrain after the bodies, as the generator builds it: PyBullet's contact order follows creation order
        add_static(
            client,
            [(entry, scene.meshes.get(entry.mesh)) for entry in scene.static],
            TABLE_2A.floor_friction,
            TABLE_2A.floor_restitution,
        )
        return tuple(bodies)

    def _apply(self, parameters: BulletParameters) -> None:
        if len(parameters.object_friction) != self.scene.n_bodies:
            raise ContactbenchError(
                f"{len(parameters.object_friction)} object frictions for a scene of {self.scene.n_bodies} bodies"
            )
        if parameters == self.parameters:
            return
        scene = articulated(self.scene, parameters.articulation)
        effects = parameters.effects
        compliance = {}
        if parameters.contact_stiffness is not None:
            compliance = {
                "contactStiffness": parameters.contact_stiffness,
                "contactDamping": parameters.contact_damping,
            }
        # PyBullet has no way back to its rigid contact for a body, nor a way to move a centre of mass: a world of the
        # scene starts afresh.
        back_to_rigid = (
            parameters.contact_stiffness is None
            and self.parameters is not None
            and self.parameters.contact_stiffness is not None
        )
        moved = (effects.com_offset, effects.inertia_scale) != self.inertial_effects
        if back_to_rigid or moved:
            if moved:
                self._inertial(effects)
            self.close()
            self.client = pybullet.connect(pybullet.DIRECT)
            self.bodies = self._build()
        pybullet.setGravity(*(self.scene.gravity * effects.gravity_scale).tolist(), physicsClientId=self.client)
        pybullet.resetBasePositionAndOrientation(
            self.floor,
            (0.0, 0.0, self.scene.floor_z + effects.floor_offset),
            rotations.wxyz_to_xyzw(rotations.tilt(*effects.floor_tilt)).tolist(),
            physicsClientId=self.client,
        )
        # Friction along world x over along world y is the anisotropy (SceneEffects), their geometric mean the body's:
        # PyBullet scales friction along the floor's own axes.
        root = float(np.sqrt(effects.friction_anisotropy))
        pybullet.changeDynamics(
            self.floor, -1, anisotropicFriction=[root, 1.0 / root, 1.0], physicsClientId=self.client
        )
        self.drag = InertiaBoxDrag(self.scene, effects, self.moments) if effects.fluid_density > 0 else None
        factor = scene.inertia_scale / self.scene.inertia_scale
        inertia = factor != self.inertia_factor
        for k, (i, link) in enumerate(self.links):
            change_dynamics(
                self.client,
                self.bodies[i],
                link,
                lateralFriction=parameters.object_friction[k],
                restitution=parameters.restitution[k],
                spinningFriction=parameters.spinning_friction,
                rollingFriction=parameters.rolling_friction,
                **compliance,
                **({"localInertiaDiagonal": (factor * self.moments[k]).tolist()} if inertia else {}),
            )
        self.inertia_factor = factor
        # Per tree with joints: its handle, its links and their dampings (N m s/rad), applied before every step.
        self.damped = []
        joints = scene.joints
        for i, tree in enumerate(self.trees):
            if not tree.joints:
                continue
            links = list(range(len(tree.joints)))
            # Coulomb friction: a velocity motor held at 0 that gives at most the friction; 0 also switches off
            # PyBullet's default motor, which would hold the joint.
            pybullet.setJointMotorControlArray(
                self.bodies[i],
                links,
                pybullet.VELOCITY_CONTROL,
                targetVelocities=[0.0] * len(links),
                forces=[joints[j].friction for j in tree.joints],
                physicsClientId=self.client,
            )
            damping = [joints[j].damping for j in tree.joints]
            if any(damping):
                self.damped.append((i, links, damping))
        self.parameters = parameters

    def _to_inertial(
        self, poses: np.ndarray, velocities: np.ndarray, bodies: np.ndarray | slice = slice(None)
    ) -> tuple[np.ndarray, np.ndarray]:
        """Mesh-frame poses [K, 7] / world velocities [K, 6] of `bodies` -> the inertial frames' (PyBullet's)."""
        offset = rotations.rotate(poses[:, 3:], self.coms[bodies])
        orientation = rotations.multiply(poses[:, 3:], self.axes[bodies])
        linear = velocities[:, :3] + np.cross(velocities[:, 3:], offset)
        return np.concatenate([poses[:, :3] + offset, orientation], axis=1), np.concatenate(
            [linear, velocities[:, 3:]], axis=1
        )

    def _to_mesh(
        self, poses: np.ndarray, velocities: np.ndarray, bodies: np.ndarray | slice = slice(None)
    ) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of _to_inertial, over leading axes: poses [..., K, 7], velocities [..., K, 6]."""
        coms, axes = self.coms[bodies], self.axes[bodies]
        orientation = rotations.multiply(poses[..., 3:], rotations.conjugate(axes))
        offset = rotations.rotate(orientation, np.broadcast_to(coms, poses.shape[:-1] + (3,)))
        linear = velocities[..., :3] - np.cross(velocities[..., 3:], offset)
        return np.concatenate([poses[..., :3] - offset, orientation], axis=-1), np.concatenate(
            [linear, velocities[..., 3:]], axis=-1
        )

    def toss(
        self, parameters: BulletParameters, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int
    ) -> tuple[np.ndarray, np.ndarray]:
        self._apply(parameters)
        if self.joints:
            return self._toss_hinged(np.asarray(poses0), np.asarray(velocities0), n_steps)
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
        if self.drag is not None:
            self._push(base_poses, base_velocities)
        for _ in range(n_steps):
            step(client)
            for body in bodies:
                record(read_pose(body, client))
                record(read_velocity(body, client))
            if self.drag is not None:
                latest = engine_states(readings[-2 * len(bodies) :], 1, len(bodies))[0]
                self._push(
                    np.concatenate([latest[:, :3], rotations.xyzw_to_wxyz(latest[:, 3:7])], axis=1), latest[:, 7:]
                )
        states = engine_states(readings, n_steps, len(bodies))
        poses, velocities = recorded_motion(states, base_poses[:, 3:])
        return (poses, velocities) if self.mesh_frames_inertial else self._to_mesh(poses, velocities)

    def _push(self, poses: np.ndarray, velocities: np.ndarray) -> None:
        """The drag (sim/effects.InertiaBoxDrag) for the next step; `poses` [K, 7] and `velocities` [K, 6] are the
        inertial frames' (PyBullet's)."""
        frames = rotations.to_matrix(poses[:, 3:])  # [K, 3, 3] principal axes in the world
        forces, torques = self.drag.wrenches(frames, velocities[:, :3], velocities[:, 3:])
        for body, pose, force, torque in zip(self.bodies, poses, forces, torques):
            pybullet.applyExternalForce(
                body, -1, force.tolist(), pose[:3].tolist(), pybullet.WORLD_FRAME, physicsClientId=self.client
            )
            pybullet.applyExternalTorque(body, -1, torque.tolist(), pybullet.WORLD_FRAME, physicsClientId=self.client)

    def _push_links(self) -> None:
        """The drag for the next step on every body of a scene with joints, a tree's base and its links alike, from
        the inertial frames and centre-of-mass velocities PyBullet reports for each."""
        client = self.client
        positions, orientations, linear, spin = [], [], [], []
        for handle_index, link in self.links:
            handle = self.bodies[handle_index]
            if link < 0:
                position, orientation = pybullet.getBasePositionAndOrientation(handle, physicsClientId=client)
                velocity, turning = pybullet.getBaseVelocity(handle, physicsClientId=client)
            else:
                state = pybullet.getLinkState(
                    handle, link, computeLinkVelocity=1, computeForwardKinematics=1, physicsClientId=client
                )
                position, orientation, velocity, turning = state[0], state[1], state[6], state[7]
            positions.append(position)
            orientations.append(orientation)
            linear.append(velocity)
            spin.append(turning)
        frames = rotations.to_matrix(rotations.xyzw_to_wxyz(np.array(orientations)))
        forces, torques = self.drag.wrenches(frames, np.array(linear), np.array(spin))
        for (handle_index, link), position, force, torque in zip(self.links, positions, forces, torques):
            handle = self.bodies[handle_index]
            pybullet.applyExternalForce(
                handle, link, force.tolist(), list(position), pybullet.WORLD_FRAME, physicsClientId=client
            )
            pybullet.applyExternalTorque(handle, link, torque.tolist(), pybullet.WORLD_FRAME, physicsClientId=client)

    def _toss_hinged(self, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        """A toss of a scene with joints: the roots' states and the joints' are read, every child placed on its
        parent by its joint's angle and rate."""
        client, bodies, joints, roots = self.client, self.bodies, self.joints, self.roots
        jointed = [(self.bodies[i], list(range(len(tree.joints)))) for i, tree in enumerate(self.trees) if tree.joints]
        # Angle 0 before parking: two links left touching would keep their contact manifold, and its warm start,
        # into this toss (links cannot be parked apart).
        for handle, links in jointed:
            for n in links:
                pybullet.resetJointState(handle, n, 0.0, 0.0, physicsClientId=client)
        forget_contacts(client, bodies)
        base_poses, base_velocities = poses0[roots], velocities0[roots]
        if not self.mesh_frames_inertial:
            base_poses, base_velocities = self._to_inertial(base_poses, base_velocities, roots)
        for body, pose, velocity in zip(bodies, base_poses, base_velocities):
            pybullet.resetBasePositionAndOrientation(
                body, pose[:3].tolist(), rotations.wxyz_to_xyzw(pose[3:]).tolist(), physicsClientId=client
            )
            pybullet.resetBaseVelocity(body, velocity[:3].tolist(), velocity[3:].tolist(), physicsClientId=client)
        for joint in joints:
            parent, child = joint.parent, joint.child
            angle, rate = hinge_coordinates(
                poses0[parent], velocities0[parent], poses0[child], velocities0[child], joint
            )
            i, n = self.links[child]
            pybullet.resetJointState(bodies[i], n, _start_angle(joint, angle), float(rate), physicsClientId=client)
        step, read_pose, read_velocity, read_joints, drive = (
            pybullet.stepSimulation,
            pybullet.getBasePositionAndOrientation,
            pybullet.getBaseVelocity,
            pybullet.getJointStates,
            pybullet.setJointMotorControlArray,
        )
        readings, joint_readings = [], []
        record, record_joints = readings.append, joint_readings.append
        if self.drag is not None:
            self._push_links()
        for _ in range(n_steps):
            for i, links, damping in self.damped:
                rates = [state[1] for state in read_joints(bodies[i], links, physicsClientId=client)]
                forces = [-d * rate for d, rate in zip(damping, rates)]
                drive(bodies[i], links, pybullet.TORQUE_CONTROL, forces=forces, physicsClientId=client)
            step(client)
            for body in bodies:
                record(read_pose(body, client))
                record(read_velocity(body, client))
            for handle, links in jointed:
                record_joints(read_joints(handle, links, physicsClientId=client))
            if self.drag is not None:
                self._push_links()
        states = engine_states(readings, n_steps, len(bodies))
        base, base_velocity = recorded_motion(states, base_poses[:, 3:])
        if not self.mesh_frames_inertial:
            base, base_velocity = self._to_mesh(base, base_velocity, roots)
        poses, velocities = np.empty((n_steps, self.scene.n_bodies, 7)), np.empty((n_steps, self.scene.n_bodies, 6))
        poses[:, roots], velocities[:, roots] = base, base_velocity
        # [n_steps, joints, 2] angle and rate, in the trees' link order
        coordinates = np.array([state[:2] for states in joint_readings for state in states]).reshape(n_steps, -1, 2)
        order = [j for tree in self.trees for j in tree.joints]
        for column, j in enumerate(order):
            joint = joints[j]
            pose, velocity = hinge_child(
                poses[:, joint.parent],
                velocities[:, joint.parent],
                joint,
                coordinates[:, column, 0],
                coordinates[:, column, 1],
            )
            if np.dot(pose[0, 3:], poses0[joint.child, 3:]) < 0:  # the recorded child quaternion's side
                pose[:, 3:] *= -1
            poses[:, joint.child], velocities[:, joint.child] = pose, velocity
        return poses, velocities
