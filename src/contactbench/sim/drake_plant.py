"""A recordings scene's bodies in a Drake MultibodyPlant (what DrakeWorld, drake_engine.py, builds for each parameter
set): their inertias, convex hulls and hull vertices with their contact properties, the hinges, the floor with the
collision filters between them, and MuJoCo's inertia-box drag as a system on the plant (see drake_engine.py's
docstring for why each is built so)."""

from __future__ import annotations

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.common.value import AbstractValue
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
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import CoulombFriction, ExternallyAppliedSpatialForce, MultibodyPlant
from pydrake.multibody.tree import FixedOffsetFrame, RevoluteJoint, RotationalInertia, SpatialInertia
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from contactbench import rotations
from contactbench.scene import Scene
from contactbench.sim.drake_scene import (
    FLOOR_POINT_STIFFNESS,
    HYDROELASTIC_RESOLUTION_HINT,
    VERTEX_RADIUS,
    DrakeParameters,
    box_extents,
    hull_vertices,
)
from contactbench.sim.effects import NO_EFFECTS, InertiaBoxDrag, SceneEffects, inertial_frames, inertials


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


def spatial_inertia(scene: Scene, k: int, effects: SceneEffects = NO_EFFECTS) -> SpatialInertia:
    centres, inertias = inertials(scene, effects)
    com, inertia = centres[k], inertias[k]
    rotational = RotationalInertia(
        inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]
    )
    return SpatialInertia.MakeFromCentralInertia(scene.bodies[k].mass, com, rotational)


def hull_shape(scene: Scene, k: int, contact_model: str) -> tuple[RigidTransform, Box | Convex]:
    """Body k's collision shape and its pose in the body frame: in point contact a Box where the hull is one (every
    cube here), else the Convex hull. In multi-body tosses Drake crashed (a segmentation fault, at random) with Convex
    hulls touching each other even from fresh contexts (see drake_engine._Simulation), less often with boxes
    (docs/results/calibration.md)."""
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
        rigid_body = plant.AddRigidBody(f"body{k}", spatial_inertia(scene, k, parameters.effects))
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
    effects = parameters.effects
    floor_pose = RigidTransform(
        Quaternion(rotations.tilt(*effects.floor_tilt)), [0.0, 0.0, scene.floor_z + effects.floor_offset]
    )
    plant.WeldFrames(plant.world_frame(), floor_body.body_frame(), floor_pose)
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


class FluidDrag(LeafSystem):
    """The inertia-box drag in moving air (sim/effects.InertiaBoxDrag, as PyBullet's world applies it) on every body
    of the plant, free or on a joint, through its applied spatial-force input."""

    def __init__(self, plant: MultibodyPlant, scene: Scene, effects: SceneEffects):
        LeafSystem.__init__(self)
        self._coms, axes, moments = inertial_frames(scene, effects)
        self._axes = rotations.to_matrix(axes)  # [K, 3, 3] principal axes in the body frame
        self._drag = InertiaBoxDrag(scene, effects, moments)
        self._plant = plant
        self._bodies = [plant.GetBodyByName(f"body{k}") for k in range(scene.n_bodies)]
        # The bodies' poses and velocities from the state by the plant's own kinematics, in a context of its own.
        self._kinematics = plant.CreateDefaultContext()
        self._state = self.DeclareVectorInputPort("state", plant.num_positions() + plant.num_velocities())
        self.DeclareAbstractOutputPort(
            "spatial_forces", lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]), self._forces
        )

    def _forces(self, context, output) -> None:
        plant, kinematics = self._plant, self._kinematics
        plant.SetPositionsAndVelocities(kinematics, self._state.Eval(context))
        poses = [plant.EvalBodyPoseInWorld(kinematics, body) for body in self._bodies]
        velocities = [plant.EvalBodySpatialVelocityInWorld(kinematics, body) for body in self._bodies]
        rotation = np.array([pose.rotation().matrix() for pose in poses])
        spin = np.array([velocity.rotational() for velocity in velocities])
        origin = np.array([velocity.translational() for velocity in velocities])
        linear = origin + np.cross(spin, np.einsum("kij,kj->ki", rotation, self._coms))  # the centres of mass'
        world_forces, world_torques = self._drag.wrenches(rotation @ self._axes, linear, spin)
        forces = []
        for body, com, force, torque in zip(self._bodies, self._coms, world_forces, world_torques):
            applied = ExternallyAppliedSpatialForce()
            applied.body_index = body.index()
            applied.p_BoBq_B = com
            applied.F_Bq_W = SpatialForce(torque, force)
            forces.append(applied)
        output.set_value(forces)


def add_fluid_drag(builder: DiagramBuilder, plant: MultibodyPlant, scene: Scene, effects: SceneEffects) -> None:
    """FluidDrag on the finalized plant's bodies (none without a fluid)."""
    if effects.fluid_density <= 0:
        return
    drag = builder.AddSystem(FluidDrag(plant, scene, effects))
    builder.Connect(plant.get_state_output_port(), drag.get_input_port(0))
    builder.Connect(drag.get_output_port(0), plant.get_applied_spatial_force_input_port())
