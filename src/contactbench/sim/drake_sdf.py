"""The scene as SDFormat for Drake's Parser (`scene_sdf`: what drake_plant.add_scene builds) and the hinges' Coulomb
friction read back from such a file (`sdf_joint_frictions`), which the parser leaves out."""

from __future__ import annotations

from pathlib import Path
from xml.etree import ElementTree

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.scene import Scene
from contactbench.sim.articulation import articulated
from contactbench.sim.drake_scene import (
    DISCRETE_CONTACT_APPROXIMATION,
    FLOOR_POINT_STIFFNESS,
    HYDROELASTIC_RESOLUTION_HINT,
    VERTEX_RADIUS,
    DrakeParameters,
    box_extents,
    hull_vertices,
)


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
