"""A recordings scene in PyBullet's terms, what the world (bullet_engine.py) and the URDF writer (bullet_urdf.py)
share: the contact parameters, the generator's world settings, the bodies' inertial frames and their trees of hinged
bodies with the link frames PyBullet gives them.

Parameters (`BulletParameters`)
-------------------------------
object_friction, restitution: per body (lateral Coulomb friction; Newton restitution of normal velocity).
spinning_friction (m): torsional friction, a torque of spinning_friction x the normal force opposing spin about the
normal; rolling_friction (m): the same against rolling. contact_stiffness (N/m) and contact_damping (N s/m): a
compliant contact (PyBullet turns them into each step's ERP = h k / (h k + d) and CFM = 1 / (h k + d)); None (both)
keeps PyBullet's own rigid contact, which resolves penetration by error reduction (what the generator uses).
articulation: a hinged scene's joint damping and friction and inertia scale (sim/articulation.py); None: as recorded.
effects: the diagnosis' effects (sim/effects.py): gravity, the floor's pose and its friction anisotropy (PyBullet's
own anisotropic friction), the bodies' centre of mass and inertia, and the inertia-box drag in moving air as a force
and torque applied before every step (free bodies).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.scene import Scene
from contactbench.sim.articulation import Articulation
from contactbench.sim.bullet_world import BulletSettings
from contactbench.sim.effects import NO_EFFECTS, SceneEffects
from contactbench.values import freeze_numbers

# the generator's engine settings: restitution threshold, floor friction and restitution
TABLE_2A = BulletSettings()


@dataclass(frozen=True)
class BulletParameters:
    """PyBullet contact parameters of a scene (see the module docstring)."""

    object_friction: tuple[float, ...]
    restitution: tuple[float, ...]
    spinning_friction: float = 0.0
    rolling_friction: float = 0.0
    contact_stiffness: float | None = None
    contact_damping: float | None = None
    articulation: Articulation | None = None
    effects: SceneEffects = NO_EFFECTS  # the diagnosis' effects (Engine.library_effects), each off by default

    def __post_init__(self):
        freeze_numbers(self, vectors=("object_friction", "restitution"), skip=("articulation", "effects"))
        if len(self.object_friction) != len(self.restitution):
            raise ContactbenchError(
                f"{len(self.object_friction)} frictions and {len(self.restitution)} restitutions "
                "(expected one per body)"
            )
        coefficients = self.object_friction + (self.spinning_friction, self.rolling_friction)
        if not all(np.isfinite(coefficients)) or min(coefficients) < 0:
            raise ContactbenchError(f"PyBullet friction coefficients must be finite and >= 0, got {self}")
        if not all(0 <= r <= 1 for r in self.restitution):
            raise ContactbenchError(f"PyBullet restitution must lie in [0, 1], got {self.restitution}")
        if (self.contact_stiffness is None) != (self.contact_damping is None):
            raise ContactbenchError("PyBullet contact_stiffness and contact_damping are given together or not at all")
        if self.contact_stiffness is not None and not (
            np.isfinite(self.contact_stiffness) and self.contact_stiffness > 0 and 0 <= self.contact_damping < np.inf
        ):
            raise ContactbenchError(
                f"PyBullet contact stiffness must be > 0 and damping >= 0, finite, got {self.contact_stiffness}, "
                f"{self.contact_damping}"
            )


@dataclass(frozen=True)
class Tree:
    """A root body and the joints (indices into `Scene.joints`) of the bodies hanging from it, in PyBullet's link
    order (link n turns on joints[n]); a free body is a tree without joints."""

    root: int
    joints: tuple[int, ...] = ()


def trees(scene: Scene) -> tuple[Tree, ...]:
    """The scene's trees of jointed bodies, in the order of their roots among the bodies."""
    joints = scene.joints  # parents first
    children = {joint.child for joint in joints}
    result = []
    for root in (k for k in range(scene.n_bodies) if k not in children):
        members, hanging = {root}, []
        for j, joint in enumerate(joints):
            if joint.parent in members:
                members.add(joint.child)
                hanging.append(j)
        result.append(Tree(root, tuple(hanging)))
    return tuple(result)


def link_origins(scene: Scene) -> np.ndarray:
    """Per body [K, 3]: the origin of its PyBullet link frame in its mesh frame, its joint's anchor (a root: 0)."""
    origins = np.zeros((scene.n_bodies, 3))
    for joint in scene.joints:
        origins[joint.child] = joint.child_anchor
    return origins
