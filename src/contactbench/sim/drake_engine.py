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
  reordering.
* Robustness (drake 1.51.1): in multi-body tosses Drake crashed with a segmentation fault in the broad phase
  (GeometryState::FinalizePoseUpdate), at random, after 5-60 tosses, when one context served toss after toss, when
  parameters were swapped into a built context (SceneGraph.AssignRole), and, less often, when convex hulls met convex
  hulls. Each parameter set got its own diagram (DrakeWorld keeps the last few; a build costs 6 ms), every toss
  starts from a clone of that diagram's template context (0.3 ms) and box-shaped hulls are Boxes (hull_shape): sixty
  three-cube tosses with one parameter set then ran through in 6 runs of 7, and a search's changing parameters still
  crashed within 8-41 candidates. DrakeEngine therefore refuses multi-body scenes (NotApplicable: a sweep skips the
  job with one line); DrakeWorld itself still builds them, for what single tosses show. Single-body scenes never
  crashed (over 200,000 tosses of identification).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

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
from pydrake.multibody.tree import RotationalInertia, SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from scipy.spatial import ConvexHull

from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.meshes import obj_text
from contactbench.recordings import Scene
from contactbench.rotations import normalize
from contactbench.sim.engines import Dimension, Engine, require_flat
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

    def __post_init__(self):
        freeze_numbers(self, vectors=("object_friction",), skip=("contact_model",))
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
    """The scene's free bodies (body<k>) with their convex hulls, their hull vertices for point contact with the
    floor (body<k>_vertices, welded to body<k>), the floor (a half space on a body welded to the world) and the
    collision filters that make hulls meet hulls and vertices meet the floor only (see the module docstring)."""
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


class _Simulation:
    """One finalized diagram of the scene for one parameter set, its simulator and where each body's state lies."""

    def __init__(self, builder: DiagramBuilder, plant: MultibodyPlant, n_bodies: int, frame_steps: int):
        self.plant = plant
        self.diagram = builder.Build()
        self.simulator = Simulator(self.diagram)
        # Every toss starts from a clone of this context (see "Robustness" in the module docstring).
        self.template = self.diagram.CreateDefaultContext()
        bodies = [plant.GetBodyByName(f"body{k}") for k in range(n_bodies)]
        # Indices into q of each body's pose (x, y, z, qw, qx, qy, qz) and into v of its (v, ω).
        self.pose_index = np.array([b.floating_positions_start() + np.r_[4:7, 0:4] for b in bodies])
        self.velocity_index = np.array([b.floating_velocities_start_in_v() + np.r_[3:6, 0:3] for b in bodies])
        self.step = plant.time_step()
        self.frame_steps = frame_steps

    def toss(self, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        n_positions = self.plant.num_positions()
        q, v = np.zeros(n_positions), np.zeros(self.plant.num_velocities())
        q[self.pose_index] = np.concatenate([poses0[:, :3], normalize(poses0[:, 3:])], axis=-1)
        v[self.velocity_index] = velocities0
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
        return states[:, self.pose_index], states[:, n_positions + self.velocity_index]


class DrakeWorld(World):
    """Drake's simulation of a scene: one diagram per parameter set, the last few kept."""

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
        builder, plant, scene_graph = new_plant(self.scene, self.substeps, parameters.contact_model)
        if self.scene_file is None:
            add_scene(plant, scene_graph, self.scene, parameters)
        else:
            Parser(plant).AddModels(str(self.scene_file))
        plant.Finalize()
        self._simulations[key] = _Simulation(builder, plant, self.scene.n_bodies, self.substeps)
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
    meshes/body<k>.obj."""
    if len(parameters.object_friction) != scene.n_bodies:
        raise ContactbenchError(f"{len(parameters.object_friction)} object frictions for {scene.n_bodies} bodies")
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
        links.append(
            f'<link name="body{k}"><inertial><pose>{_xml_numbers(com)} 0 0 0</pose>'
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
                f'<link name="body{k}_vertices">{massless}{spheres}</link>'
                f'<joint name="body{k}_vertices_weld" type="fixed"><parent>body{k}</parent>'
                f"<child>body{k}_vertices</child></joint>"
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
            f"{DISCRETE_CONTACT_APPROXIMATION.name}: SDFormat carries none of these (contactbench.sim.drake_engine."
            "new_plant sets them). The meshes are in meshes/ beside this file. -->",
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
        require_flat(scene, "Drake")
        if scene.n_bodies > 1:
            raise NotApplicable(
                f"the Drake engine simulates single-body scenes; {scene.name} has {scene.n_bodies} bodies (drake "
                "1.51.1 crashed with a segmentation fault at random in body-body contact, see sim/drake_engine.py)"
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
