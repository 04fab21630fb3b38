"""Drake as a contactbench engine: a MultibodyPlant of any recordings scene and its rollouts (the contact parameters,
what they mean and Drake's defaults: drake_scene.py; the scene as SDFormat: drake_sdf.py).

Simulation
----------
* Body frame = the recordings' mesh frame; the spatial inertia is the scene's mass, centre of mass and central
  inertia. Bodies collide with each other by their meshes' convex hulls (a ``Box`` where the hull is one, else a
  ``Convex`` built in memory from the vertices; see hull_shape and _Simulation for the crashes this avoids). Point
  contact gives one contact point per pair of geometries, so a hull on the floor half space rocks forever between
  corners (a flat-resting cube did at every approximation and step we tried); in point contact the
  floor therefore meets each hull vertex instead (a sphere of VERTEX_RADIUS on a massless body welded to the body),
  which is exact for a convex hull against a plane and gives each touching vertex a contact of stiffness k: a cube
  resting on a face sinks m g / (4 k). Collision filters keep hulls off the floor and vertices off everything but
  the floor. Two hulls still touch at one point (a body resting on another may rock).
* Hydroelastic contact uses the hulls against the floor: a cube at rest stays at rest, but dropped cubes kept
  rocking at the recordings' frame steps in our measurements (moduli 1e4..1e7 Pa), so it stays an option.
* Discrete plant, time step = dt / substeps, Drake's semi-implicit stepping (v += h a, then q += h N(q) v).
* Contact approximation: TAMSI (``DISCRETE_CONTACT_APPROXIMATION``), measured against SAP's "lagged" and "similar" on
  real-cube tosses over parameter sets spanning SysID's box (docs/results/calibration.md): none failed or gained
  energy with any of the three, TAMSI was the fastest, and TAMSI is the approximation of the Drake of Acosta et al.
  2022. ("sap" itself ignores Hunt–Crossley dissipation.) Should TAMSI fail to converge, the toss
  raises and SteppedRollouts turns it into an unstable (NaN) candidate.
* A free body's state is q = (qw, qx, qy, qz, x, y, z) of its frame in world and v = (ω, v) in world: exactly the
  recordings' pose (reordered) and world velocity of the mesh-frame origin, so no conversion is needed beyond the
  reordering (and normalizing the quaternion, which Drake's discrete step lets drift off unit length).

Hinges (recordings version 2 ``joints``)
----------------------------------------
* A hinge j is a RevoluteJoint ``hinge<j>`` from a frame at the parent's anchor to one at the child's, both parallel
  to their bodies' mesh frames, about the recorded axis: the child's frame is the parent's turned by the joint angle,
  as the recordings define it, and the anchors coincide by construction. Its damping is the joint's own (Drake
  applies it implicitly in the discrete step) and its range Drake's joint limits. The base of each tree of bodies is
  free; a toss starts from the base's pose and velocity and each joint's angle and rate
  (kinematics.hinge_coordinates), and every child's mesh-frame pose and world velocity are read back from its
  parent's and the joint's state (kinematics.hinge_child, exact Drake kinematics).
* Joint Coulomb friction (``Joint.friction``, N m): Drake's discrete plant has none, so JointFriction (a LeafSystem
  on the plant's applied generalized force input) applies, against each joint's rate, the torque that would stop the
  joint within one step, capped at the friction: Coulomb friction regularized over rates below f h (M⁻¹)_jj. A force
  evaluated at the start of the step, as the plant's inputs are, chatters about zero rate with a sharper
  regularization; this one lets a joint under torques below f stick.
* A hinge's two links collide with each other (Drake's default filter between bodies adjacent through a joint is off:
  new_plant), since the elbow's bars touch when it folds.
* ``DrakeParameters.articulation`` (sim/articulation.py), when not None, replaces the joints' damping and friction
  and scales every body's inertia: the world simulates ``articulated(scene, articulation)``.

Robustness (drake 1.51.1)
-------------------------
In multi-body tosses Drake crashes its process with a segmentation fault in the broad phase
(GeometryState::FinalizePoseUpdate), at random: when one context served toss after toss, when parameters were swapped
into a built context (SceneGraph.AssignRole), less often with a diagram per parameter set, and in every search of
changing candidates (three cubes with random parameter sets, whether or not old diagrams are destroyed; a toss that
crashed ran through when run again alone in a fresh process). Each parameter set gets its own diagram (DrakeWorld
keeps the last few), every toss starts from a clone of that diagram's template context and box-shaped hulls are
Boxes (hull_shape), which make crashes rarer; what makes them harmless is that DrakeWorld says ``in_process = False``:
sim/stepped.SteppedRollouts then runs every toss in worker processes, even with one thread, and a crashed worker costs
only the tosses it ran, each run again in a fresh process (NaN, an unstable candidate, only where a toss kills a
fresh process of its own). Where TAMSI, the discrete solver, fails to converge at a frame (a stiff contact at the
recordings' step: untuned Drake on a few real elbow tosses), the toss goes on from its last frame in a diagram of the
same parameters stepping finer (FALLBACK_REFINEMENTS, in turn); only a toss that fails at the finest is unstable.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
from pydrake.geometry import SceneGraph
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, ContactModel, MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.kinematics import hinge_child, hinge_coordinates
from contactbench.meshes import obj_text
from contactbench.rotations import normalize
from contactbench.scene import Scene
from contactbench.sim.articulation import articulated
from contactbench.sim.drake_plant import add_fluid_drag, add_scene
from contactbench.sim.drake_scene import (
    DISCRETE_CONTACT_APPROXIMATION,
    DRAKE_DEFAULT_DISSIPATION,
    DRAKE_DEFAULT_FRICTION,
    DRAKE_DEFAULT_POINT_STIFFNESS,
    DrakeParameters,
)
from contactbench.sim.drake_sdf import mesh_file_name, scene_sdf, sdf_joint_frictions
from contactbench.sim.effects import SceneEffects
from contactbench.sim.engines import Dimension, Engine
from contactbench.sim.stepped import SteppedRollouts, World

# Every world here has a floor half space and no deformable body: Drake's warning, at every diagram built, that half
# spaces take no part in deformable contact is about nothing these worlds simulate.
HALF_SPACE_NOTE = "Rigid (non-deformable) half spaces are not currently supported for deformable contact"
logging.getLogger("drake").addFilter(lambda record: not record.getMessage().startswith(HALF_SPACE_NOTE))

SIMULATIONS_KEPT = 4  # diagrams a world keeps, least recently used first out (a search asks a generation at a time)
DIVERGED = 1e4  # m or m/s (rad/s): a toss state beyond this has blown up; its frames from there on are NaN
FALLBACK_REFINEMENTS = (4, 16)  # steps a frame, in turn, where the solver failed at the recordings' step


def new_plant(scene: Scene, substeps: int, contact_model: str) -> tuple[DiagramBuilder, MultibodyPlant, SceneGraph]:
    """A builder with an empty discrete plant (time step dt / substeps, the scene's gravity, our contact settings)
    and its SceneGraph, ready for the scene's bodies."""
    if substeps < 1:
        raise ContactbenchError(f"substeps must be a positive integer, got {substeps}")
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=scene.dt / substeps)
    plant.set_discrete_contact_approximation(DISCRETE_CONTACT_APPROXIMATION)
    plant.set_contact_model(ContactModel.kPoint if contact_model == "point" else ContactModel.kHydroelastic)
    plant.mutable_gravity_field().set_gravity_vector(scene.gravity)
    # Without sampled output ports the state is q and v alone: setting them resets a toss completely.
    plant.SetUseSampledOutputPorts(False)
    # A hinge's links collide with each other (the elbow's bars touch when it folds); our own filters keep a body's
    # vertex spheres off its hull, which is all the plant's filter of adjacent bodies would do besides.
    plant.set_adjacent_bodies_collision_filters(False)
    return builder, plant, scene_graph


class JointFriction(LeafSystem):
    """Coulomb friction of the hinges as a generalized force on the plant's applied-force input: against each joint's
    rate, the torque that stops the joint within one step, at most its friction f. That is Coulomb friction
    regularized over rates below f h (M⁻¹)_jj (h the plant's step, M the mass matrix at the step's start), the
    sharpest regularization that lets a joint under torques below f stick instead of chattering: the plant reads this
    input at the start of each step. Drake's discrete plant has no joint Coulomb friction of its own."""

    def __init__(self, plant: MultibodyPlant, rate_index: np.ndarray, frictions: np.ndarray):
        LeafSystem.__init__(self)
        self._plant, self._plant_context = plant, plant.CreateDefaultContext()
        self._rate_index, self._frictions = rate_index, frictions
        self._n_positions, self._step = plant.num_positions(), plant.time_step()
        self._state = self.DeclareVectorInputPort("state", plant.num_positions() + plant.num_velocities())
        self.DeclareVectorOutputPort("generalized_force", plant.num_velocities(), self._generalized_force)

    def _generalized_force(self, context, output) -> None:
        state = self._state.Eval(context)
        self._plant.SetPositionsAndVelocities(self._plant_context, state)
        mobility = np.linalg.inv(self._plant.CalcMassMatrix(self._plant_context)).diagonal()[self._rate_index]
        rates = state[self._n_positions + self._rate_index]
        force = np.zeros(self._plant.num_velocities())
        force[self._rate_index] = -np.clip(rates / (self._step * mobility), -self._frictions, self._frictions)
        output.SetFromVector(force)


def add_joint_friction(builder: DiagramBuilder, plant: MultibodyPlant, frictions: list[float]) -> None:
    """JointFriction of the finalized plant's hinges hinge<j> (none where every friction is 0)."""
    if not any(frictions):
        return
    rate_index = np.array([plant.GetJointByName(f"hinge{j}").velocity_start() for j in range(len(frictions))])
    friction = builder.AddSystem(JointFriction(plant, rate_index, np.asarray(frictions, dtype=np.float64)))
    builder.Connect(plant.get_state_output_port(), friction.get_input_port(0))
    builder.Connect(friction.get_output_port(0), plant.get_applied_generalized_force_input_port())


class _Simulation:
    """One finalized diagram of the scene for one parameter set, its simulator and where each body's state lies: a
    free body's pose and velocity in its floating joint's, a hinge's child as the joint's angle and rate."""

    def __init__(self, builder: DiagramBuilder, plant: MultibodyPlant, scene: Scene, frame_steps: int):
        self.plant = plant
        self.diagram = builder.Build()
        self.simulator = Simulator(self.diagram)
        # Every toss starts from a clone of this context (see "Robustness" in the module docstring).
        self.template = self.diagram.CreateDefaultContext()
        self.n_bodies, self.joints = scene.n_bodies, scene.joints
        children = {joint.child for joint in self.joints}
        self.free = np.array([k for k in range(scene.n_bodies) if k not in children], dtype=np.int64)
        bodies = [plant.GetBodyByName(f"body{k}") for k in self.free]
        # Indices into q of each free body's pose (x, y, z, qw, qx, qy, qz) and into v of its (v, ω).
        self.pose_index = np.array([b.floating_positions_start() + np.r_[4:7, 0:4] for b in bodies])
        self.velocity_index = np.array([b.floating_velocities_start_in_v() + np.r_[3:6, 0:3] for b in bodies])
        hinges = [plant.GetJointByName(f"hinge{j}") for j in range(len(self.joints))]
        self.angle_index = np.array([hinge.position_start() for hinge in hinges], dtype=np.int64)
        self.rate_index = np.array([hinge.velocity_start() for hinge in hinges], dtype=np.int64)
        self.step = plant.time_step()
        self.frame_steps = frame_steps

    def toss(
        self, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int
    ) -> tuple[np.ndarray, np.ndarray, int | None]:
        """Poses and world velocities of frames 1..n_steps (NaN from a diverged frame) and the frame at which the
        discrete solver failed to converge (None: it never did)."""
        n_positions = self.plant.num_positions()
        q, v = np.zeros(n_positions), np.zeros(self.plant.num_velocities())
        poses0 = np.concatenate([poses0[:, :3], normalize(poses0[:, 3:])], axis=-1)
        q[self.pose_index] = poses0[self.free]
        v[self.velocity_index] = velocities0[self.free]
        for joint, angle_at, rate_at in zip(self.joints, self.angle_index, self.rate_index):
            q[angle_at], v[rate_at] = hinge_coordinates(
                poses0[joint.parent], velocities0[joint.parent], poses0[joint.child], velocities0[joint.child], joint
            )
        self.simulator.reset_context(self.template.Clone())
        context = self.simulator.get_mutable_context()
        plant_context = self.plant.GetMyMutableContextFromRoot(context)
        self.plant.SetPositionsAndVelocities(plant_context, np.concatenate([q, v]))
        self.simulator.Initialize()
        states = np.full((n_steps, n_positions + len(v)), np.nan)
        failed_at = None
        for frame in range(n_steps):
            # The time of the frame's last step, computed as Drake computes its periodic update times.
            try:
                self.simulator.AdvanceTo((frame + 1) * self.frame_steps * self.step)
            except RuntimeError as error:
                if "failed to converge" not in str(error):
                    raise
                failed_at = frame
                break
            state = self.plant.GetPositionsAndVelocities(plant_context)
            # A diverged state must not reach the next step: non-finite or runaway poses corrupt the broad phase's
            # bounding-box tree, and Drake crashed (a segmentation fault in FinalizePoseUpdate) in multi-body tosses.
            if not np.abs(state).max() < DIVERGED:
                break
            states[frame] = state
        poses, velocities = np.full((n_steps, self.n_bodies, 7), np.nan), np.full((n_steps, self.n_bodies, 6), np.nan)
        free_poses = states[:, self.pose_index]
        # Drake's discrete step lets a free body's quaternion drift off unit length; a hinge's child is placed by it.
        poses[:, self.free] = np.concatenate([free_poses[..., :3], normalize(free_poses[..., 3:])], axis=-1)
        velocities[:, self.free] = states[:, n_positions + self.velocity_index]
        for joint, angle_at, rate_at in zip(self.joints, self.angle_index, self.rate_index):  # parents first
            poses[:, joint.child], velocities[:, joint.child] = hinge_child(
                poses[:, joint.parent],
                velocities[:, joint.parent],
                joint,
                states[:, angle_at],
                states[:, n_positions + rate_at],
            )
        return poses, velocities, failed_at


class DrakeWorld(World):
    """Drake's simulation of a scene: one diagram per parameter set, the last few kept."""

    in_process = False  # drake 1.51.1 may crash its process (see "Robustness" in the module docstring)

    def __init__(self, scene: Scene, substeps: int = 1, scene_file: str | Path | None = None):
        """A world built from the scene; with `scene_file` (an SDFormat file of scene_file's kind, meshes beside it),
        the bodies and their properties are parsed from it instead and toss ignores its parameters."""
        self.scene, self.substeps = scene, int(substeps)
        self.scene_file = scene_file
        self._simulations: OrderedDict[DrakeParameters | str, _Simulation] = OrderedDict()

    def _simulation(self, parameters: DrakeParameters, refinement: int = 1) -> _Simulation:
        """The diagram of these parameters, built with them: replacing proximity properties in a built context
        (SceneGraph.AssignRole) crashed Drake 1.51.1 in multi-body searches, where building costs a few ms.
        `refinement` > 1: the same scene stepping that many times per step of the world (the solver's fallback)."""
        key = (parameters if self.scene_file is None else parameters.contact_model, refinement)
        if key in self._simulations:
            self._simulations.move_to_end(key)
            return self._simulations[key]
        scene = articulated(self.scene, parameters.articulation) if self.scene_file is None else self.scene
        substeps = self.substeps * refinement
        builder, plant, scene_graph = new_plant(scene, substeps, parameters.contact_model)
        plant.mutable_gravity_field().set_gravity_vector(scene.gravity * parameters.effects.gravity_scale)
        if self.scene_file is None:
            add_scene(plant, scene_graph, scene, parameters)
            frictions = [joint.friction for joint in scene.joints]
        else:
            Parser(plant).AddModels(str(self.scene_file))
            frictions = sdf_joint_frictions(self.scene_file, len(scene.joints))
        plant.Finalize()
        add_joint_friction(builder, plant, frictions)
        if self.scene_file is None:
            add_fluid_drag(builder, plant, scene, parameters.effects)
        self._simulations[key] = _Simulation(builder, plant, scene, substeps)
        if len(self._simulations) > SIMULATIONS_KEPT:
            self._simulations.popitem(last=False)
        return self._simulations[key]

    def toss(
        self, parameters: DrakeParameters, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int
    ) -> tuple[np.ndarray, np.ndarray]:
        if len(parameters.object_friction) != self.scene.n_bodies:
            raise ContactbenchError(
                f"{len(parameters.object_friction)} object frictions for a scene of {self.scene.n_bodies} bodies"
            )
        poses0, velocities0 = np.asarray(poses0, dtype=np.float64), np.asarray(velocities0, dtype=np.float64)
        poses, velocities, failed_at = self._simulation(parameters).toss(poses0, velocities0, n_steps)
        for refinement in FALLBACK_REFINEMENTS:
            if failed_at is None:
                break
            start = (poses0, velocities0) if failed_at == 0 else (poses[failed_at - 1], velocities[failed_at - 1])
            rest_poses, rest_velocities, failed_again = self._simulation(parameters, refinement).toss(
                *start, n_steps - failed_at
            )
            poses[failed_at:], velocities[failed_at:] = rest_poses, rest_velocities
            failed_at = None if failed_again is None else failed_at + failed_again
        return poses, velocities

    def close(self) -> None:
        self._simulations.clear()


class DrakeEngine(Engine):
    """Drake's compliant point contact (or hydroelastic) in a discrete MultibodyPlant."""

    name = "drake"

    def library_effects(self, scene: Scene) -> frozenset[str]:
        """Gravity, the floor's pose, the bodies' centre of mass and inertia, and drag in moving air; Drake's contact
        has no anisotropic, rolling or torsional friction."""
        return frozenset(
            {"gravity_scale", "floor_offset", "floor_tilt", "com_offset", "inertia_mismatch", "air_drag", "wind"}
        )

    def with_effects(
        self,
        parameters: DrakeParameters,
        effects: SceneEffects,
        rolling_friction: float = 0.0,
        torsional_friction: float = 0.0,
    ) -> DrakeParameters:
        if rolling_friction or torsional_friction or effects.friction_anisotropy != 1.0:
            raise NotApplicable("Drake's contact has no rolling, torsional or anisotropic friction")
        return replace(parameters, effects=effects)

    def default_parameters(self, n_bodies: int) -> DrakeParameters:
        return DrakeParameters(
            object_friction=(DRAKE_DEFAULT_FRICTION,) * n_bodies,
            floor_friction=DRAKE_DEFAULT_FRICTION,
            point_stiffness=DRAKE_DEFAULT_POINT_STIFFNESS,
            hunt_crossley_dissipation=DRAKE_DEFAULT_DISSIPATION,
        )

    def dimensions(self, n_bodies: int) -> tuple[Dimension, ...]:
        return (
            *(Dimension(f"object_friction_{k}", 0.0, 1.0) for k in range(n_bodies)),
            Dimension("floor_friction", 0.0, 1.0),
            Dimension("point_stiffness", 1e2, 1e7, log=True, init=1e4),
            Dimension("hunt_crossley_dissipation", 1e-2, 1e2, log=True, init=1.0),
        )

    def from_values(self, values: Mapping[str, float], n_bodies: int) -> DrakeParameters:
        return DrakeParameters(
            object_friction=tuple(values[f"object_friction_{k}"] for k in range(n_bodies)),
            floor_friction=values["floor_friction"],
            point_stiffness=values["point_stiffness"],
            hunt_crossley_dissipation=values["hunt_crossley_dissipation"],
        )

    def to_values(self, parameters: DrakeParameters) -> dict[str, float]:
        return {
            **{f"object_friction_{k}": mu for k, mu in enumerate(parameters.object_friction)},
            "floor_friction": parameters.floor_friction,
            "point_stiffness": parameters.point_stiffness,
            "hunt_crossley_dissipation": parameters.hunt_crossley_dissipation,
        }

    def check_scene(self, scene: Scene) -> None:
        missing = [
            what
            for what, present in (
                ("static terrain", scene.static),
                ("non-convex bodies (pieces)", not all(scene.is_convex(k) for k in range(scene.n_bodies))),
            )
            if present
        ]
        if missing:
            raise NotApplicable(
                f"the Drake engine simulates convex bodies, free or hinged, on the flat floor; {scene.name} has "
                f"{' and '.join(missing)} (model=sysid and mujoco_default simulate those)"
            )

    def rollouts(self, scene: Scene, nthread: int | None = None, substeps: int = 1) -> SteppedRollouts:
        self.check_scene(scene)
        return SteppedRollouts(scene, DrakeWorld, nthread, substeps)

    def scene_files(self, scene: Scene, parameters: DrakeParameters, substeps: int = 1) -> dict[str, str]:
        """scene.sdf (loaded with pydrake's Parser into a plant made by new_plant) and the meshes it refers to."""
        files = {"scene.sdf": scene_sdf(scene, parameters, substeps)}
        for k in range(scene.n_bodies):
            files[mesh_file_name(k)] = obj_text(scene.body_mesh(k), f"{scene.bodies[k].name}: mesh frame = body frame")
        return files
