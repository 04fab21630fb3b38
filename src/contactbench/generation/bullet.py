"""PyBullet toss simulation for the generator, in the benchmark's PyBullet world (sim/bullet_world.py)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from contactbench import rotations
from contactbench.generation.effects import NONE, ConcealedEffects
from contactbench.generation.scenes import SceneSpec
from contactbench.meshes import Mesh
from contactbench.scene import Static
from contactbench.sim.bullet_world import (
    BODY_DYNAMICS_OVERRIDES,
    BulletSettings,
    add_static,
    convex_compound,
    engine_states,
    forget_contacts,
    parking_spot,
    recorded_motion,
    table_2a_world,
)
from contactbench.sim.quiet_pybullet import pybullet

CONTACT_KEYS = ("contact_normal_force", "contact_friction_force", "contact_normal_torque", "contact_friction_torque")


class BulletScene:
    """A private PyBullet DIRECT world with a floor and `spec.bodies` copies of `mesh`, reusable across tosses."""

    def __init__(
        self,
        mesh: Mesh,
        spec: SceneSpec,
        settings: BulletSettings = BulletSettings(),
        effects: ConcealedEffects = NONE,
        pieces: Sequence[Mesh] = (),
        static: Sequence[tuple[Static, Mesh | None]] = (),
    ):
        """`mesh` is each body's true surface (its mass properties), `pieces` the convex solids it collides as
        (default: the mesh's hull), `static` the terrain besides the floor (entries and their meshes)."""
        com, inertia = mesh.mass_properties(settings.mass)
        if np.linalg.norm(com) > 1e-9 * mesh.width:
            raise ValueError(f"mesh frame must sit at the centre of mass; it is off by {com} m")
        if np.abs(inertia - np.diag(np.diag(inertia))).max() > 1e-9 * np.trace(inertia):
            raise ValueError("mesh axes must be principal axes of inertia (PyBullet takes a diagonal inertia here)")
        self.spec = spec
        self.settings = settings
        self.effects = effects
        self.inertia_diagonal = np.diag(inertia).copy()
        self.com_offset = np.array(effects.com_offset)
        # Fluid drag by MuJoCo's inertia-box law (its docs, "Fluid forces"): the body acts as the box with its
        # inertia, half-sizes r; per body axis i, force -2 rho r_j r_k |u_i| u_i and torque
        # -1/2 rho r_i (r_j^4 + r_k^4) |w_i| w_i, with u the body-frame velocity relative to the wind.
        true_inertia = self.inertia_diagonal * np.array(effects.inertia_scale)
        half = np.sqrt(1.5 / settings.mass * np.maximum(true_inertia.sum() - 2 * true_inertia, 0.0))
        j, k = [1, 0, 0], [2, 2, 1]
        self.drag_force = 2.0 * effects.fluid_density * half[j] * half[k]
        self.drag_torque = 0.5 * effects.fluid_density * half * (half[j] ** 4 + half[k] ** 4)
        self.spin_damping_torque = effects.spin_damping * true_inertia  # per body axis, times the spin there
        self.client = pybullet.connect(pybullet.DIRECT)
        try:
            self.floor, self.bodies = self._build(list(pieces) or [mesh])
            self.static = add_static(self.client, static, settings.floor_friction, settings.floor_restitution)
        except BaseException:
            self.close()
            raise

    def _build(self, pieces: list[Mesh]) -> tuple[int, tuple[int, ...]]:
        settings, spec, client = self.settings, self.spec, self.client
        table_2a_world(client, settings, np.asarray(settings.gravity) * self.effects.gravity_scale)
        floor_shape = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client)
        floor = pybullet.createMultiBody(
            0.0,
            floor_shape,
            basePosition=(0.0, 0.0, self.effects.floor_offset),
            baseOrientation=rotations.wxyz_to_xyzw(rotations.tilt(*self.effects.floor_tilt)).tolist(),
            physicsClientId=client,
        )
        # PyBullet combines two touching materials by multiplying their frictions and their restitutions, so
        # with the floor at 1.0 and 1.0 the object's own coefficients are the ones in effect.
        pybullet.changeDynamics(
            floor,
            -1,
            lateralFriction=settings.floor_friction,
            restitution=settings.floor_restitution,
            rollingFriction=0.0,
            spinningFriction=0.0,
            anisotropicFriction=(*self.effects.floor_friction_scale, 1.0),
            physicsClientId=client,
        )
        body_shape = convex_compound(client, pieces)
        bodies = []
        for k in range(spec.bodies):
            body = pybullet.createMultiBody(
                settings.mass,
                body_shape,
                basePosition=parking_spot(k),
                baseInertialFramePosition=self.com_offset.tolist(),
                physicsClientId=client,
            )
            pybullet.changeDynamics(
                body,
                -1,
                mass=settings.mass,
                localInertiaDiagonal=(self.inertia_diagonal * self.effects.inertia_scale).tolist(),
                lateralFriction=spec.friction,
                restitution=spec.restitution,
                physicsClientId=client,
                **{
                    **BODY_DYNAMICS_OVERRIDES,
                    "rollingFriction": self.effects.rolling_friction,
                    "spinningFriction": self.effects.spinning_friction,
                },
            )
            bodies.append(body)
        return floor, tuple(bodies)

    def _offset_world(self, orientations: np.ndarray) -> np.ndarray:
        """The centre of mass relative to the mesh frame, world frame, for orientations [..., 4] (w-first)."""
        return rotations.rotate(orientations, np.broadcast_to(self.com_offset, orientations.shape[:-1] + (3,)))

    def close(self) -> None:
        if self.client >= 0:
            pybullet.disconnect(physicsClientId=self.client)
            self.client = -1

    def __enter__(self) -> BulletScene:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def set_state(self, poses: np.ndarray, velocities: np.ndarray) -> None:
        """Place the bodies at poses [K, 7] (w-first) with velocities [K, 6] (world frame), forgetting past contacts."""
        poses = np.asarray(poses, dtype=np.float64)
        velocities = np.asarray(velocities, dtype=np.float64)
        count = len(self.bodies)
        if poses.shape != (count, 7) or velocities.shape != (count, 6):
            raise ValueError(
                f"expected poses [{count}, 7] and velocities [{count}, 6], got {poses.shape} and {velocities.shape}"
            )
        client = self.client
        forget_contacts(client, self.bodies)
        orientations_xyzw = rotations.wxyz_to_xyzw(poses[:, 3:])
        if self.com_offset.any():  # PyBullet places and reports a body by its centre of mass
            offset = self._offset_world(poses[:, 3:])
            poses = np.concatenate([poses[:, :3] + offset, poses[:, 3:]], axis=1)
            velocities = np.concatenate(
                [velocities[:, :3] + np.cross(velocities[:, 3:], offset), velocities[:, 3:]], axis=1
            )
        for body, pose, orientation, velocity in zip(self.bodies, poses, orientations_xyzw, velocities):
            pybullet.resetBasePositionAndOrientation(body, pose[:3], orientation, physicsClientId=client)
            pybullet.resetBaseVelocity(body, velocity[:3], velocity[3:], physicsClientId=client)

    def simulate(
        self, initial_poses: np.ndarray, initial_velocities: np.ndarray, frames: int, *, record_contacts: bool = False
    ) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Toss from the initial state and record `frames` frames (frame 0 = initial state, one engine step each).

        Returns poses [T, K, 7] (w-first) and velocities [T, K, 6], world frame; with record_contacts also a dict
        of the CONTACT_KEYS arrays [T, K, 3] (see `_contact_wrenches`), frame 0 all zeros.
        """
        states, contacts = self.toss(initial_poses, initial_velocities, frames, record_contacts=record_contacts)
        poses, velocities = recorded_motion(states, np.asarray(initial_poses)[:, 3:])
        if not record_contacts:
            return poses, velocities
        return poses, velocities, contacts

    def toss(
        self, initial_poses: np.ndarray, initial_velocities: np.ndarray, frames: int, *, record_contacts: bool = False
    ) -> tuple[np.ndarray, dict[str, np.ndarray] | None]:
        """Like `simulate`, but the states as PyBullet reports them, [T, K, 13] (see `recorded_motion`), so that a
        batch of tosses can be converted at once; the contact wrenches are None without record_contacts."""
        if frames < 1:
            raise ValueError(f"frames must be at least 1, got {frames}")
        self.set_state(initial_poses, initial_velocities)
        client, bodies = self.client, self.bodies
        step, read_pose, read_velocity = (
            pybullet.stepSimulation,
            pybullet.getBasePositionAndOrientation,
            pybullet.getBaseVelocity,
        )
        # The two state reads per body and frame alone cost about half as much as stepping (1 us each through
        # PyBullet's command layer); keep everything else out of the loop: collect PyBullet's tuples, convert once.
        readings = []
        record = readings.append
        contact_log: list[tuple[int, tuple]] = []
        drag = self._apply_forces if self.effects.applied_forces else None
        for t in range(frames):
            if t:
                step(client)
                if record_contacts:
                    contact_log.extend((t, point) for point in pybullet.getContactPoints(physicsClientId=client))
            for body in bodies:
                record(read_pose(body, client))
                record(read_velocity(body, client))
            if drag:
                drag(readings[-2 * len(bodies) :])
        states = engine_states(readings, frames, len(bodies))
        # Torques are taken about the centres of mass, which PyBullet reports: before moving to the mesh frames.
        contacts = self._contact_wrenches(contact_log, states[..., :3]) if record_contacts else None
        if self.com_offset.any():
            states = self._mesh_frame_states(states)
        return states, contacts

    def _apply_forces(self, latest: list[tuple]) -> None:
        """Fluid force and torque (see __init__) and the outside-library accelerations for the next step, at each
        centre of mass."""
        effects = self.effects
        wind = np.array(effects.wind)
        for body, (pose, velocity) in zip(self.bodies, zip(latest[::2], latest[1::2])):
            rotation = rotations.to_matrix(rotations.xyzw_to_wxyz(np.array(pose[1])))
            linear, angular = np.array(velocity[0]), np.array(velocity[1])
            relative = rotation.T @ (linear - wind)
            spin = rotation.T @ angular
            force = rotation @ (-self.drag_force * np.abs(relative) * relative)
            torque = rotation @ (-self.drag_torque * np.abs(spin) * spin - self.spin_damping_torque * spin)
            acceleration = -2 * effects.coriolis * np.cross([0.0, 0.0, 1.0], linear)
            if (effects.floor_viscosity or effects.floor_centring) and pybullet.getContactPoints(
                body, self.floor, physicsClientId=self.client
            ):
                place = np.array(pose[0][:2])
                acceleration[:2] -= effects.floor_viscosity * linear[:2] + effects.floor_centring * place
            force = force + self.settings.mass * acceleration
            pybullet.applyExternalForce(
                body, -1, force.tolist(), pose[0], pybullet.WORLD_FRAME, physicsClientId=self.client
            )
            pybullet.applyExternalTorque(body, -1, torque.tolist(), pybullet.WORLD_FRAME, physicsClientId=self.client)

    def _mesh_frame_states(self, states: np.ndarray) -> np.ndarray:
        """Engine states [T, K, 13] of the centres of mass -> of the mesh frames (position and linear velocity)."""
        states = states.copy()
        offset = self._offset_world(rotations.xyzw_to_wxyz(states[..., 3:7]))
        states[..., :3] -= offset
        states[..., 7:10] -= np.cross(states[..., 10:13], offset)
        return states

    def _contact_wrenches(self, contact_log: list[tuple[int, tuple]], centres: np.ndarray) -> dict[str, np.ndarray]:
        """Per-frame, per-body contact forces (N) and torques about the centre of mass (N m), [T, K, 3] each.

        PyBullet reports each contact's impulse divided by dt, so m (v_t - v_{t-1}) / dt = m g + total force at
        frame t. The impulses act at the contact points found before the step, so torques are taken about the
        centres of mass before the step, `centres` [T, K, 3] at frame t - 1. Floor and body-body contacts count.
        """
        frames, count = centres.shape[:2]
        result = {key: np.zeros((frames, count, 3)) for key in CONTACT_KEYS}
        if not contact_log:
            return result
        index_of = {body: k for k, body in enumerate(self.bodies)}
        frame = np.array([t for t, _ in contact_log])
        points = [point for _, point in contact_log]
        # Per contact: body A, body B, point on A, point on B, normal on B (pointing to A), the normal force and
        # two friction forces along their directions, all as applied to body A; B gets the opposite.
        body_a = np.array([index_of.get(c[1], count) for c in points])  # index `count` collects the floor's share
        body_b = np.array([index_of.get(c[2], count) for c in points])
        point_a = np.array([c[5] for c in points])
        point_b = np.array([c[6] for c in points])
        normal_force = np.array([c[9] for c in points])[:, None] * np.array([c[7] for c in points])
        friction_force = np.array([c[10] for c in points])[:, None] * np.array([c[11] for c in points]) + np.array(
            [c[12] for c in points]
        )[:, None] * np.array([c[13] for c in points])
        padded_centres = np.concatenate([centres, np.zeros((frames, 1, 3))], axis=1)
        for body, point, sign in ((body_a, point_a, 1.0), (body_b, point_b, -1.0)):
            arm = point - padded_centres[frame - 1, body]
            for part, force in (("normal", normal_force), ("friction", friction_force)):
                force_sum = np.zeros((frames, count + 1, 3))
                torque_sum = np.zeros((frames, count + 1, 3))
                np.add.at(force_sum, (frame, body), sign * force)
                np.add.at(torque_sum, (frame, body), np.cross(arm, sign * force))
                result[f"contact_{part}_force"] += force_sum[:, :count]
                result[f"contact_{part}_torque"] += torque_sum[:, :count]
        return result
