"""Drake as a contactbench engine: a MultibodyPlant of any recordings scene, its contact parameters and rollouts.

Parameters and what they mean physically
----------------------------------------
* ``object_friction[k]``, ``floor_friction``: Coulomb coefficients of body k's and the floor's material. Drake
  combines two materials' coefficients per contact pair as μ = 2 μ1 μ2 / (μ1 + μ2) (its own rule, applied by Drake;
  both static and dynamic coefficients get the same value: the discrete solvers use the dynamic one only). As with
  MuJoCo's Table 2c parameters, identification searches the per-body and the floor coefficients; their combination
  is Drake's.
* ``point_stiffness`` (N/m): compliant point contact's spring, f_n = k x (1 + d ẋ) with penetration x.
* ``hunt_crossley_dissipation`` d (s/m): the Hunt–Crossley damping of the same law; the coefficient of
  restitution falls roughly as 1 / (1 + d v) with impact speed v.
* ``contact_model``: "point" (compliant point contact, what Acosta et al. 2022 tuned) or "hydroelastic", in which
  every body is compliant hydroelastic with ``hydroelastic_modulus`` (Pa) against a rigid hydroelastic floor
  (pressure field contact; bodies collide with each other compliant-compliant); friction and dissipation act as in
  point contact and ``point_stiffness`` is unused.

Drake combines the two geometries' stiffnesses in series, k = k1 k2 / (k1 + k2), and their dissipations weighted
by stiffness, d = k2/(k1+k2) d1 + k1/(k1+k2) d2 (moduli in place of stiffnesses for hydroelastic). So that the
identified numbers are a floor contact's own values, every body carries ``point_stiffness`` and
``hunt_crossley_dissipation`` and the floor carries FLOOR_POINT_STIFFNESS (1e15 N/m: a floor contact's stiffness is
the body's to a relative 1e-8 for k <= 1e7) and the same dissipation (so the weighted mean is exactly d); in
hydroelastic contact the floor is rigid, so a floor contact has the body's modulus and dissipation exactly. Contacts
between two bodies have stiffness k/2 (in series), dissipation d and the harmonic-mean friction of the two bodies.

Defaults
--------
DrakeEngine.default_parameters are what MultibodyPlant uses when a geometry has no proximity properties, from
``pydrake.geometry.DefaultProximityProperties()`` in drake 1.51.1 (drake/geometry/scene_graph_config.h): friction
0.5 (static and dynamic), point stiffness 1e6 N/m, Hunt–Crossley dissipation 50 s/m, hydroelastic modulus 1e7 Pa.

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
* Contact approximation: TAMSI (``DISCRETE_CONTACT_APPROXIMATION``), measured against SAP's "lagged" and "similar" at
  the real cube's dt = 6.76 ms over 17 parameter sets (point stiffness 1e2..1e7 N/m log-uniform, dissipation
  0.01..100 s/m, Drake's defaults) x 8 real tosses of 140 frames: none failed or gained energy with any of the
  three, TAMSI took 11 ms per toss against 22 (lagged) and 33 (similar), and TAMSI is the approximation of the Drake
  of Acosta et al. 2022. ("sap" itself ignores Hunt–Crossley dissipation.) Should TAMSI fail to converge, the toss
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
fresh process of its own).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
from pydrake.geometry import (
    AddCompliantHydroelasticProperties,
    AddContactMaterial,
    AddRigidHydroelasticProperties,
    Box,
    CollisionFilterDeclaration,
    Convex,
    GeometrySet,
    HalfSpace,
    ProximityProperties,
    SceneGraph,
    Sphere,
)
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlantSceneGraph,
    ContactModel,
    CoulombFriction,
    DiscreteContactApproximation,
    MultibodyPlant,
)
from pydrake.multibody.tree import FixedOffsetFrame, RevoluteJoint, RotationalInertia, SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from scipy.spatial import ConvexHull

from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.kinematics import hinge_child, hinge_coordinates
from contactbench.meshes import obj_text
from contactbench.recordings import Scene
from contactbench.rotations import normalize
from contactbench.sim.articulation import Articulation, articulated
from contactbench.sim.engines import Dimension, Engine
from contactbench.sim.stepped import SteppedRollouts, World
from contactbench.values import freeze_numbers

CONTACT_MODELS = ("point", "hydroelastic")
DISCRETE_CONTACT_APPROXIMATION = DiscreteContactApproximation.kTamsi
# m: the spheres marking hull vertices (SDFormat refuses radius 0); contact starts this far before a vertex touches.
VERTEX_RADIUS = 1e-9
FLOOR_POINT_STIFFNESS = 1e15  # N/m: in series with a body's k <= 1e7 it changes the pair's k by at most 1e-8
# Tessellation size of hydroelastic meshes; a Convex's pressure field is built from its hull whatever the hint, which
# only affects primitives (spheres, cylinders), so any value serves.
HYDROELASTIC_RESOLUTION_HINT = 0.01
# drake 1.51.1 geometry::DefaultProximityProperties (see the module docstring).
DRAKE_DEFAULT_FRICTION = 0.5
DRAKE_DEFAULT_POINT_STIFFNESS = 1e6
DRAKE_DEFAULT_DISSIPATION = 50.0
DRAKE_DEFAULT_HYDROELASTIC_MODULUS = 1e7
SIMULATIONS_KEPT = 4  # diagrams a world keeps, least recently used first out (a search asks a generation at a time)
DIVERGED = 1e4  # m or m/s (rad/s): a toss state beyond this has blown up; its frames from there on are NaN


@dataclass(frozen=True)
class DrakeParameters:
    """Drake's contact parameters (see the module docstring for their meaning and how Drake combines them)."""

    object_friction: tuple[float, ...]  # Coulomb coefficient per body, in the recordings' body order
    floor_friction: float
    point_stiffness: float  # N/m, every body (floor contacts: exactly this)
    hunt_crossley_dissipation: float  # s/m
    contact_model: str = "point"  # "point" or "hydroelastic"
    hydroelastic_modulus: float = DRAKE_DEFAULT_HYDROELASTIC_MODULUS  # Pa, every body; hydroelastic contact only
    articulation: Articulation | None = None  # hinged scenes: joint damping, friction and inertia; None: as recorded

    def __post_init__(self):
        freeze_numbers(self, vectors=("object_friction",), skip=("contact_model", "articulation"))
        frictions = self.object_friction + (self.floor_friction,)
        if self.contact_model not in CONTACT_MODELS:
            raise ContactbenchError(f"Drake contact_model must be one of {CONTACT_MODELS}, got {self.contact_model!r}")
        if not (np.isfinite(frictions).all() and min(frictions, default=0.0) >= 0):
            raise ContactbenchError(f"Drake friction coefficients must be finite and non-negative, got {frictions}")
        if not 0 < self.point_stiffness < np.inf or not 0 < self.hydroelastic_modulus < np.inf:
            raise ContactbenchError(
                f"Drake point stiffness and hydroelastic modulus must be positive and finite, got "
                f"{self.point_stiffness} N/m and {self.hydroelastic_modulus} Pa"
            )
        if not 0 <= self.hunt_crossley_dissipation < np.inf:
            raise ContactbenchError(
                f"Drake Hunt-Crossley dissipation must be non-negative and finite, got {self.hunt_crossley_dissipation}"
            )


def body_properties(parameters: DrakeParameters, k: int) -> ProximityProperties:
    """Body k's proximity properties."""
    properties = ProximityProperties()
    friction = parameters.object_friction[k]
    AddContactMaterial(
        parameters.hunt_crossley_dissipation,
        parameters.point_stiffness,
        CoulombFriction(friction, friction),
        properties,
    )
    if parameters.contact_model == "hydroelastic":
        AddCompliantHydroelasticProperties(HYDROELASTIC_RESOLUTION_HINT, parameters.hydroelastic_modulus, properties)
    return properties


def floor_properties(parameters: DrakeParameters) -> ProximityProperties:
    """The floor's proximity properties: stiff and rigid, so that a floor contact has the body's values."""
    properties = ProximityProperties()
    friction = parameters.floor_friction
    AddContactMaterial(
        parameters.hunt_crossley_dissipation,
        FLOOR_POINT_STIFFNESS,
        CoulombFriction(friction, friction),
        properties,
    )
    if parameters.contact_model == "hydroelastic":
        AddRigidHydroelasticProperties(properties)
    return properties


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


def spatial_inertia(scene: Scene, k: int) -> SpatialInertia:
    com, inertia = scene.inertial(k)
    rotational = RotationalInertia(
        inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]
    )
    return SpatialInertia.MakeFromCentralInertia(scene.bodies[k].mass, com, rotational)


def hull_vertices(scene: Scene, k: int) -> np.ndarray:
    """The vertices [V, 3] of body k's convex hull, mesh frame."""
    vertices = scene.body_mesh(k).vertices
    return vertices[ConvexHull(vertices).vertices]


def box_extents(scene: Scene, k: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Centre and size of body k's hull if it is a box along its mesh axes, else None."""
    corners = hull_vertices(scene, k)
    low, high = corners.min(axis=0), corners.max(axis=0)
    tolerance = 1e-9 * scene.body_mesh(k).width
    on_corners = np.all(np.minimum(np.abs(corners - low), np.abs(corners - high)) <= tolerance)
    return ((low + high) / 2, high - low) if len(corners) == 8 and on_corners else None


def hull_shape(scene: Scene, k: int, contact_model: str) -> tuple[RigidTransform, Box | Convex]:
    """Body k's collision shape and its pose in the body frame: in point contact a Box where the hull is one (every
    cube here), else the Convex hull. In multi-body tosses Drake 1.51.1 crashed (a segmentation fault, at random after
    5-60 tosses) with Convex hulls touching each other in 1 of 4 runs of 60 tosses even from fresh contexts (see
    _Simulation), with boxes in 1 of 7."""
    box = box_extents(scene, k) if contact_model == "point" else None
    if box is not None:
        return RigidTransform(box[0]), Box(*box[1])
    return RigidTransform(), Convex(np.ascontiguousarray(scene.body_mesh(k).vertices.T), scene.bodies[k].name)


def add_scene(plant: MultibodyPlant, scene_graph: SceneGraph, scene: Scene, parameters: DrakeParameters) -> None:
    """The scene's bodies (body<k>) with their convex hulls, their hull vertices for point contact with the floor
    (body<k>_vertices, welded to body<k>), its hinges (add_hinges; every other body is free), the floor (a half space
    on a body welded to the world) and the collision filters that make hulls meet hulls and vertices meet the floor
    only (see the module docstring)."""
    hulls, vertices = [], []
    for k in range(scene.n_bodies):
        rigid_body = plant.AddRigidBody(f"body{k}", spatial_inertia(scene, k))
        pose, hull = hull_shape(scene, k, parameters.contact_model)
        properties = body_properties(parameters, k)
        hulls.append(plant.RegisterCollisionGeometry(rigid_body, pose, hull, f"body{k}", properties))
        if parameters.contact_model == "point":
            corners = plant.AddRigidBody(f"body{k}_vertices", SpatialInertia.Zero())
            plant.WeldFrames(rigid_body.body_frame(), corners.body_frame())
            for i, vertex in enumerate(hull_vertices(scene, k)):
                vertices.append(
                    plant.RegisterCollisionGeometry(
                        corners, RigidTransform(vertex), Sphere(VERTEX_RADIUS), f"body{k}_vertex{i}", properties
                    )
                )
    add_hinges(plant, scene)
    floor_body = plant.AddRigidBody("floor", SpatialInertia.Zero())
    plant.WeldFrames(plant.world_frame(), floor_body.body_frame(), RigidTransform([0.0, 0.0, scene.floor_z]))
    floor = plant.RegisterCollisionGeometry(
        floor_body, RigidTransform(), HalfSpace(), "floor", floor_properties(parameters)
    )
    if parameters.contact_model == "point":
        scene_graph.collision_filter_manager().Apply(
            CollisionFilterDeclaration()
            .ExcludeBetween(GeometrySet(hulls), GeometrySet(floor))
            .ExcludeBetween(GeometrySet(vertices), GeometrySet(hulls))
            .ExcludeWithin(GeometrySet(vertices))
        )


def add_hinges(plant: MultibodyPlant, scene: Scene) -> None:
    """Each hinge j as RevoluteJoint hinge<j> between frames at the two anchors, parallel to the bodies' frames, about
    the hinge's axis, with its damping and range (Drake's own joint limits)."""
    for j, joint in enumerate(scene.joints):
        frames = [
            plant.AddFrame(
                FixedOffsetFrame(
                    f"hinge{j}_on_body{k}", plant.GetBodyByName(f"body{k}").body_frame(), RigidTransform(anchor)
                )
            )
            for k, anchor in ((joint.parent, joint.parent_anchor), (joint.child, joint.child_anchor))
        ]
        low, high = joint.range if joint.range is not None else (-np.inf, np.inf)
        plant.AddJoint(RevoluteJoint(f"hinge{j}", *frames, joint.axis, low, high, joint.damping))


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

    def toss(self, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
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
        for frame in range(n_steps):
            # The time of the frame's last step, computed as Drake computes its periodic update times.
            self.simulator.AdvanceTo((frame + 1) * self.frame_steps * self.step)
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
        return poses, velocities


class DrakeWorld(World):
    """Drake's simulation of a scene: one diagram per parameter set, the last few kept."""

    in_process = False  # drake 1.51.1 may crash its process (see "Robustness" in the module docstring)

    def __init__(self, scene: Scene, substeps: int = 1, scene_file: str | Path | None = None):
        """A world built from the scene; with `scene_file` (an SDFormat file of scene_file's kind, meshes beside it),
        the bodies and their properties are parsed from it instead and toss ignores its parameters."""
        self.scene, self.substeps = scene, int(substeps)
        self.scene_file = scene_file
        self._simulations: OrderedDict[DrakeParameters | str, _Simulation] = OrderedDict()

    def _simulation(self, parameters: DrakeParameters) -> _Simulation:
        """The diagram of these parameters, built with them: replacing proximity properties in a built context
        (SceneGraph.AssignRole) crashed Drake 1.51.1 in multi-body searches, where building costs a few ms."""
        key = parameters if self.scene_file is None else parameters.contact_model
        if key in self._simulations:
            self._simulations.move_to_end(key)
            return self._simulations[key]
        scene = articulated(self.scene, parameters.articulation) if self.scene_file is None else self.scene
        builder, plant, scene_graph = new_plant(scene, self.substeps, parameters.contact_model)
        if self.scene_file is None:
            add_scene(plant, scene_graph, scene, parameters)
            frictions = [joint.friction for joint in scene.joints]
        else:
            Parser(plant).AddModels(str(self.scene_file))
            frictions = sdf_joint_frictions(self.scene_file, len(scene.joints))
        plant.Finalize()
        add_joint_friction(builder, plant, frictions)
        self._simulations[key] = _Simulation(builder, plant, scene, self.substeps)
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
        return self._simulation(parameters).toss(
            np.asarray(poses0, dtype=np.float64), np.asarray(velocities0, dtype=np.float64), n_steps
        )

    def close(self) -> None:
        self._simulations.clear()


def _xml_numbers(values) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(values))


def _collision_xml(name: str, pose, geometry: str, friction: float, stiffness: float, parameters, extra: str) -> str:
    number = _xml_numbers
    return (
        f'<collision name="{name}"><pose>{number(pose)} 0 0 0</pose><geometry>{geometry}</geometry>'
        f"<drake:proximity_properties><drake:mu_dynamic>{number(friction)}</drake:mu_dynamic>"
        f"<drake:mu_static>{number(friction)}</drake:mu_static>"
        f"<drake:point_contact_stiffness>{number(stiffness)}</drake:point_contact_stiffness>"
        f"<drake:hunt_crossley_dissipation>{number(parameters.hunt_crossley_dissipation)}"
        f"</drake:hunt_crossley_dissipation>{extra}</drake:proximity_properties></collision>"
    )


def mesh_file_name(k: int) -> str:
    """Body k's mesh, relative to scene.sdf."""
    return f"meshes/body{k}.obj"


def _filter_group(name: str, members: list[str], ignored: list[str]) -> str:
    return (
        f'<drake:collision_filter_group name="{name}">'
        + "".join(f"<drake:member>{member}</drake:member>" for member in members)
        + "".join(f"<drake:ignored_collision_filter_group>{g}</drake:ignored_collision_filter_group>" for g in ignored)
        + "</drake:collision_filter_group>"
    )


def scene_sdf(scene: Scene, parameters: DrakeParameters, substeps: int = 1) -> str:
    """SDFormat text of what add_scene builds, with these parameters; it refers to body k's mesh as
    meshes/body<k>.obj. A hinge is a revolute joint hinge<j> with its damping and its Coulomb friction in
    <dynamics><friction>, which Drake's parser does not apply: DrakeWorld reads it back (sdf_joint_frictions)."""
    if len(parameters.object_friction) != scene.n_bodies:
        raise ContactbenchError(f"{len(parameters.object_friction)} object frictions for {scene.n_bodies} bodies")
    scene = articulated(scene, parameters.articulation)
    parent_of = {joint.child: joint for joint in scene.joints}
    point = parameters.contact_model == "point"
    body_extra, floor_extra = "", ""
    if not point:
        body_extra = (
            f"<drake:compliant_hydroelastic/><drake:hydroelastic_modulus>{_xml_numbers(parameters.hydroelastic_modulus)}"
            f"</drake:hydroelastic_modulus><drake:mesh_resolution_hint>{HYDROELASTIC_RESOLUTION_HINT!r}"
            "</drake:mesh_resolution_hint>"
        )
        floor_extra = "<drake:rigid_hydroelastic/>"
    massless = "<inertial><mass>0</mass><inertia><ixx>0</ixx><iyy>0</iyy><izz>0</izz></inertia></inertial>"
    links = []
    for k in range(scene.n_bodies):
        com, inertia = scene.inertial(k)
        friction, stiffness = parameters.object_friction[k], parameters.point_stiffness
        moments = "".join(
            f"<i{a}>{_xml_numbers(inertia[i, j])}</i{a}>"
            for a, (i, j) in {
                "xx": (0, 0),
                "yy": (1, 1),
                "zz": (2, 2),
                "xy": (0, 1),
                "xz": (0, 2),
                "yz": (1, 2),
            }.items()
        )
        box = box_extents(scene, k) if point else None
        hull_pose = np.zeros(3) if box is None else box[0]
        hull = (
            f"<mesh><uri>{mesh_file_name(k)}</uri><drake:declare_convex/></mesh>"
            if box is None
            else f"<box><size>{_xml_numbers(box[1])}</size></box>"
        )
        # A hinge's child sits where angle 0 puts it; the state of a toss places every body anyway.
        placed = (
            f'<pose relative_to="body{parent_of[k].parent}">'
            f"{_xml_numbers(parent_of[k].parent_anchor - parent_of[k].child_anchor)} 0 0 0</pose>"
            if k in parent_of
            else ""
        )
        links.append(
            f'<link name="body{k}">{placed}<inertial><pose>{_xml_numbers(com)} 0 0 0</pose>'
            f"<mass>{_xml_numbers(scene.bodies[k].mass)}</mass><inertia>{moments}</inertia></inertial>"
            f"{_collision_xml(f'body{k}', hull_pose, hull, friction, stiffness, parameters, body_extra)}</link>"
        )
        if point:
            spheres = "".join(
                _collision_xml(
                    f"body{k}_vertex{i}",
                    vertex,
                    f"<sphere><radius>{VERTEX_RADIUS!r}</radius></sphere>",
                    friction,
                    stiffness,
                    parameters,
                    "",
                )
                for i, vertex in enumerate(hull_vertices(scene, k))
            )
            links.append(
                f'<link name="body{k}_vertices"><pose relative_to="body{k}"/>{massless}{spheres}</link>'
                f'<joint name="body{k}_vertices_weld" type="fixed"><parent>body{k}</parent>'
                f"<child>body{k}_vertices</child></joint>"
            )
    for j, joint in enumerate(scene.joints):
        limits = "" if joint.range is None else f"<lower>{joint.range[0]!r}</lower><upper>{joint.range[1]!r}</upper>"
        links.append(
            f'<joint name="hinge{j}" type="revolute"><pose>{_xml_numbers(joint.child_anchor)} 0 0 0</pose>'
            f"<parent>body{joint.parent}</parent><child>body{joint.child}</child><axis><xyz>{_xml_numbers(joint.axis)}"
            f"</xyz><limit>{limits}<effort>0</effort></limit><dynamics><damping>{joint.damping!r}</damping>"
            f"<friction>{joint.friction!r}</friction></dynamics></axis></joint>"
        )
    floor = _collision_xml(
        "floor",
        np.zeros(3),
        "<plane><normal>0 0 1</normal></plane>",
        parameters.floor_friction,
        FLOOR_POINT_STIFFNESS,
        parameters,
        floor_extra,
    )
    filters = []
    if point:
        hulls, vertices = (
            [f"body{k}" for k in range(scene.n_bodies)],
            [f"body{k}_vertices" for k in range(scene.n_bodies)],
        )
        filters = [
            _filter_group("hull_group", hulls, ["floor_group"]),
            _filter_group("vertex_group", vertices, ["hull_group", "vertex_group"]),
            _filter_group("floor_group", ["floor"], []),
        ]
    return "\n".join(
        [
            '<?xml version="1.0"?>',
            f"<!-- {scene.name}: the plant is discrete with time_step {float(scene.dt / substeps)!r} s, gravity "
            f"{_xml_numbers(scene.gravity)} m/s^2, {parameters.contact_model} contact, discrete contact approximation "
            f"{DISCRETE_CONTACT_APPROXIMATION.name}, hinged links colliding with each other: SDFormat carries none "
            "of these (contactbench.sim.drake_engine.new_plant sets them), and Drake applies no joint <friction> "
            "(drake_engine.add_joint_friction does). The meshes are in meshes/ beside this file. -->",
            '<sdf version="1.9" xmlns:drake="http://drake.mit.edu">',
            '<model name="scene">',
            *links,
            f'<link name="floor"><pose>0 0 {_xml_numbers(scene.floor_z)} 0 0 0</pose>{massless}{floor}</link>',
            '<joint name="floor_weld" type="fixed"><parent>world</parent><child>floor</child></joint>',
            *filters,
            "</model>",
            "</sdf>",
        ]
    )


def sdf_joint_frictions(path: str | Path, n_joints: int) -> list[float]:
    """The Coulomb friction (N m) of hinges hinge0..hinge<n_joints - 1> in a scene_sdf file."""
    joints = {joint.get("name"): joint for joint in ElementTree.parse(path).getroot().iter("joint")}
    return [float(joints[f"hinge{j}"].findtext("axis/dynamics/friction", "0")) for j in range(n_joints)]


class DrakeEngine(Engine):
    """Drake's compliant point contact (or hydroelastic) in a discrete MultibodyPlant."""

    name = "drake"

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
