"""What identification tunes of a hinged scene besides contact, the same for every engine: each hinge's damping and
Coulomb friction, and one scale on the links' inertia.

An `Articulation` is a field of every engine's parameters (None: the scene as recorded). Engines apply it by simulating
`articulated(scene, articulation)`, a copy of the scene with those values, so that the joint's physics is written in
one place per engine (the scene builder), whatever set it.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.scene import Scene
from contactbench.sim.engines import Dimension
from contactbench.values import freeze_numbers

# Search ranges. A link of the real elbow (0.37 kg, 10 cm) has about 8e-4 kg m^2 about its hinge: damping 0.1 N m s/rad
# all but locks it within a frame, friction 0.1 N m holds it against most of its own weight's torque. Inertia: a factor
# of 2 either way around the uniform-density solid the meshes give.
JOINT_DAMPING = (0.0, 0.1)
JOINT_FRICTION = (0.0, 0.1)
INERTIA_SCALE = (0.5, 2.0)


@dataclass(frozen=True)
class Articulation:
    """Per joint (in `Scene.joints` order): damping (N m s/rad) and Coulomb friction (N m); `inertia_scale` multiplies
    every body's inertia tensor (mass and centre of mass stay)."""

    joint_damping: tuple[float, ...]
    joint_friction: tuple[float, ...]
    inertia_scale: float = 1.0

    def __post_init__(self):
        freeze_numbers(self, vectors=("joint_damping", "joint_friction"))
        values = self.joint_damping + self.joint_friction
        if len(self.joint_damping) != len(self.joint_friction):
            raise ContactbenchError(
                f"{len(self.joint_damping)} joint dampings and {len(self.joint_friction)} frictions (expected one per "
                "joint)"
            )
        if not (all(np.isfinite(values)) and min(values, default=0.0) >= 0):
            raise ContactbenchError(f"joint damping and friction must be finite and >= 0, got {self}")
        if not (np.isfinite(self.inertia_scale) and self.inertia_scale > 0):
            raise ContactbenchError(f"the inertia scale must be finite and > 0, got {self.inertia_scale}")

    @classmethod
    def recorded(cls, scene: Scene) -> Articulation:
        """The scene's own values: its joints' damping and friction, its inertia."""
        joints = scene.joints
        return cls(
            tuple(joint.damping for joint in joints), tuple(joint.friction for joint in joints), scene.inertia_scale
        )


def dimensions(n_joints: int) -> tuple[Dimension, ...]:
    """The searched articulation of a scene with `n_joints` hinges (none without hinges: a free body's inertia is
    left to its mesh, as the paper's Table 2c does)."""
    if n_joints == 0:
        return ()
    return (
        *(Dimension(f"joint_damping_{j}", *JOINT_DAMPING, init=0.0) for j in range(n_joints)),
        *(Dimension(f"joint_friction_{j}", *JOINT_FRICTION, init=0.0) for j in range(n_joints)),
        Dimension("inertia_scale", *INERTIA_SCALE, log=True, init=1.0),
    )


def from_values(values: Mapping[str, float], n_joints: int) -> Articulation | None:
    if n_joints == 0:
        return None
    return Articulation(
        tuple(float(values[f"joint_damping_{j}"]) for j in range(n_joints)),
        tuple(float(values[f"joint_friction_{j}"]) for j in range(n_joints)),
        float(values["inertia_scale"]),
    )


def to_values(articulation: Articulation | None) -> dict[str, float]:
    if articulation is None:
        return {}
    return (
        {f"joint_damping_{j}": d for j, d in enumerate(articulation.joint_damping)}
        | {f"joint_friction_{j}": f for j, f in enumerate(articulation.joint_friction)}
        | {"inertia_scale": articulation.inertia_scale}
    )


def articulated(scene: Scene, articulation: Articulation | None) -> Scene:
    """The scene with these joint dampings, frictions and inertia scale (the scene itself where None)."""
    if articulation is None:
        return scene
    joints = scene.joints
    if len(articulation.joint_damping) != len(joints):
        raise ContactbenchError(
            f"{scene.name}: an articulation of {len(articulation.joint_damping)} joints for a scene of {len(joints)}"
        )
    meta = copy.deepcopy(scene.meta)
    names = [body["name"] for body in meta["bodies"]]
    by_child = {entry["child"]: entry for entry in meta.get("joints", [])}  # a body is the child of one joint at most
    for joint, damping, friction in zip(joints, articulation.joint_damping, articulation.joint_friction):
        by_child[names[joint.child]]["damping"] = damping
        by_child[names[joint.child]]["friction"] = friction
    return replace(scene, meta=meta, inertia_scale=articulation.inertia_scale)
