"""The fitted scene as URDF for PyBullet (`scene_files`): a robot per free body or tree of hinged bodies, the
terrain, and their meshes."""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np

from contactbench import rotations
from contactbench.meshes import obj_text
from contactbench.scene import Joint, Scene
from contactbench.sim.articulation import articulated
from contactbench.sim.bullet_scene import TABLE_2A, BulletParameters, link_origins, trees
from contactbench.sim.bullet_world import BODY_DYNAMICS_OVERRIDES
from contactbench.sim.effects import inertial_frames


def _numbers(values) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(values))


def _roll_pitch_yaw(q: np.ndarray) -> np.ndarray:
    """URDF's rpy of a rotation (w-first quaternion): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    m = rotations.to_matrix(q)
    return np.array([np.arctan2(m[2, 1], m[2, 2]), -np.arcsin(np.clip(m[2, 0], -1, 1)), np.arctan2(m[1, 0], m[0, 0])])


def scene_files(scene: Scene, parameters: BulletParameters) -> dict[str, str]:
    """One URDF per free body or tree of hinged bodies (body_<k>.urdf, k its root: pybullet.loadURDF with
    flags=URDF_USE_INERTIA_FROM_FILE, else PyBullet computes an inertia of its own from the collision shape): a link
    per body with its inertial frame, its convex pieces (meshes/body_<k>_<i>.obj, one <collision> each; a convex body
    has one) and its contact parameters in PyBullet's <contact> extension, and per hinge a continuous (revolute, with a
    range) joint at the anchor with its damping and friction in <dynamics>; terrain as static_<i>.urdf (mass 0; a
    height field as its triangle surface); the world settings (step, gravity, the floor and its material) and how the
    world drives the hinges are stated in a comment, as the generator sets them."""
    scene = articulated(scene, parameters.articulation)
    coms, axes, moments = inertial_frames(scene)
    origins, joints = link_origins(scene), scene.joints
    world = (
        f"PyBullet world: fixedTimeStep {scene.dt!r} s, gravity {_numbers(scene.gravity)}, a plane at z = "
        f"{scene.floor_z!r} with lateral friction {TABLE_2A.floor_friction!r} and restitution "
        f"{TABLE_2A.floor_restitution!r} (PyBullet multiplies the two materials' coefficients), "
        f"restitutionVelocityThreshold {TABLE_2A.restitution_velocity_threshold!r}, numSubSteps 0; load with "
        "flags=URDF_USE_INERTIA_FROM_FILE; after loading: "
        + ", ".join(f"{key} {value!r}" for key, value in BODY_DYNAMICS_OVERRIDES.items() if key != "collisionMargin")
    )
    hinged = (
        "; hinges: load with flags=URDF_USE_INERTIA_FROM_FILE | URDF_USE_SELF_COLLISION | "
        "URDF_USE_SELF_COLLISION_INCLUDE_PARENT (the links collide with one another), then per joint "
        "setJointMotorControl2(VELOCITY_CONTROL, targetVelocity=0, force=<dynamics friction>) and before every step "
        "setJointMotorControl2(TORQUE_CONTROL, force=-<dynamics damping> x the joint rate)"
    )
    names = [quoteattr(body.name) for body in scene.bodies]

    def link(k: int) -> list[str]:
        compliance = ""
        if parameters.contact_stiffness is not None:
            stiffness, damping = parameters.contact_stiffness, parameters.contact_damping
            compliance = f'<stiffness value="{stiffness!r}"/><damping value="{damping!r}"/>'
        # a child's link frame is its joint's, at the anchor: its mesh frame sits at minus the anchor there
        mesh = f'<origin xyz="{_numbers(-origins[k])}" rpy="0 0 0"/>' if origins[k].any() else ""
        return [
            f"<link name={names[k]}>",
            f'<contact><lateral_friction value="{parameters.object_friction[k]!r}"/>'
            f'<restitution value="{parameters.restitution[k]!r}"/>'
            f'<spinning_friction value="{parameters.spinning_friction!r}"/>'
            f'<rolling_friction value="{parameters.rolling_friction!r}"/>{compliance}</contact>',
            f'<inertial><origin xyz="{_numbers(coms[k] - origins[k])}" rpy="{_numbers(_roll_pitch_yaw(axes[k]))}"/>'
            f'<mass value="{scene.bodies[k].mass!r}"/><inertia ixx="{float(moments[k][0])!r}" ixy="0" ixz="0" '
            f'iyy="{float(moments[k][1])!r}" iyz="0" izz="{float(moments[k][2])!r}"/></inertial>',
            *(
                f'<collision>{mesh}<geometry><mesh filename="meshes/body_{k}_{i}.obj"/></geometry></collision>'
                for i in range(len(scene.body_pieces(k)))
            ),
            f'<visual>{mesh}<geometry><mesh filename="meshes/body_{k}.obj"/></geometry></visual>',
            "</link>",
        ]

    def hinge(joint: Joint) -> list[str]:
        limit = ""
        if joint.range is not None:
            limit = f'<limit lower="{joint.range[0]!r}" upper="{joint.range[1]!r}" effort="0" velocity="0"/>'
        return [
            f'<joint name={quoteattr(joint.name)} type="{"revolute" if limit else "continuous"}">',
            f"<parent link={names[joint.parent]}/><child link={names[joint.child]}/>",
            f'<origin xyz="{_numbers(joint.parent_anchor - origins[joint.parent])}" rpy="0 0 0"/>',
            f'<axis xyz="{_numbers(joint.axis)}"/>{limit}',
            f'<dynamics damping="{joint.damping!r}" friction="{joint.friction!r}"/>',
            "</joint>",
        ]

    files = {}
    for tree in trees(scene):
        members = [tree.root] + [joints[j].child for j in tree.joints]
        files[f"body_{tree.root}.urdf"] = "\n".join(
            [
                "<?xml version='1.0'?>",
                f"<!-- {world}{hinged if tree.joints else ''} -->",
                f"<robot name={names[tree.root]}>",
                *(line for k in members for line in link(k)),
                *(line for j in tree.joints for line in hinge(joints[j])),
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
