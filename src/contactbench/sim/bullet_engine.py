"""PyBullet as an identifiable engine: its parameter space, the effects it models, the scenes it builds (the world it
tosses: bullet_tosses.py; parameters and bodies: bullet_scene.py; URDF of the fitted scene: bullet_urdf.py)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

from contactbench.errors import NotApplicable
from contactbench.scene import Scene
from contactbench.sim.bullet_scene import TABLE_2A, BulletParameters
from contactbench.sim.bullet_tosses import BulletWorld
from contactbench.sim.bullet_urdf import scene_files
from contactbench.sim.effects import EFFECT_NAMES, SceneEffects
from contactbench.sim.engines import Dimension, Engine
from contactbench.sim.stepped import SteppedRollouts

# What a recordings hinge may say (RECORDINGS.md, version 2), all of which the world builds
HINGE_FIELDS = frozenset(
    ("name", "type", "parent", "child", "parent_anchor", "child_anchor", "axis", "damping", "friction", "range")
)
CONTACT_MODES = ("rigid", "compliant")


class BulletEngine(Engine):
    """PyBullet 3 (Bullet's sequential-impulse solver), the engine that generated the synthetic datasets."""

    name = "bullet"

    def library_effects(self, scene: Scene) -> frozenset[str]:
        """Every effect, on free and hinged bodies alike."""
        return frozenset(EFFECT_NAMES)

    def with_effects(
        self,
        parameters: BulletParameters,
        effects: SceneEffects,
        rolling_friction: float = 0.0,
        torsional_friction: float = 0.0,
    ) -> BulletParameters:
        """PyBullet's own rolling and spinning friction; the rest as BulletParameters.effects (bullet_scene.py)."""
        return replace(
            parameters,
            effects=effects,
            rolling_friction=rolling_friction or parameters.rolling_friction,
            spinning_friction=torsional_friction or parameters.spinning_friction,
        )

    def check_scene(self, scene: Scene) -> None:
        """Hinges with anchors, axis, damping, friction and range are built; any other kind of joint or joint field
        is refused, naming it, rather than simulated without it."""
        for j, entry in enumerate(scene.meta.get("joints", []) if scene.joints else []):
            if entry.get("type") != "hinge":
                raise NotApplicable(
                    f"{scene.name}: joints[{j}] field 'type' is {entry.get('type')!r}; PyBullet builds hinges only"
                )
            unknown = sorted(set(entry) - HINGE_FIELDS)
            if unknown:
                raise NotApplicable(
                    f"{scene.name}: joints[{j}] field {unknown[0]!r} is not one the PyBullet engine can build (it "
                    f"knows {', '.join(sorted(HINGE_FIELDS))})"
                )

    def default_parameters(self, n_bodies: int) -> BulletParameters:
        """PyBullet's own body defaults: friction 0.5, restitution 0, no spinning or rolling friction, rigid contact."""
        return BulletParameters(object_friction=(0.5,) * n_bodies, restitution=(0.0,) * n_bodies)

    def dimensions(self, n_bodies: int) -> tuple[Dimension, ...]:
        per_body = [Dimension(f"object_friction_{k}", 0.0, 1.0) for k in range(n_bodies)]
        per_body += [Dimension(f"restitution_{k}", 0.0, 1.0, init=0.2) for k in range(n_bodies)]
        return (
            *per_body,
            # Log scales from "none to speak of" up: the lower end moves the tosses by a negligible fraction of a
            # width, where the generator has none.
            Dimension("spinning_friction", 1e-6, 1e-2, log=True, init=1e-4),
            Dimension("rolling_friction", 1e-6, 1e-2, log=True, init=1e-4),
            # PyBullet's rigid contact (error reduction with split impulses) is not a limit of its compliant one: at
            # 1e9 N/m the compliant contact still moved the frictioncubes' tosses 0.06 widths off the rigid ones.
            Dimension("contact", choices=CONTACT_MODES),
            Dimension("contact_stiffness", 1e3, 1e8, log=True, init=1e5, when=("contact", "compliant")),
            # Damping relative to stiffness x the Table 2a step: ERP = 1 / (1 + ratio) at that step.
            Dimension("contact_damping_ratio", 0.0, 10.0, init=4.0, when=("contact", "compliant")),
        )

    def from_values(self, values: Mapping[str, float], n_bodies: int) -> BulletParameters:
        compliant = CONTACT_MODES[int(round(values["contact"]))] == "compliant"
        stiffness = float(values["contact_stiffness"])
        return BulletParameters(
            object_friction=tuple(float(values[f"object_friction_{k}"]) for k in range(n_bodies)),
            restitution=tuple(float(values[f"restitution_{k}"]) for k in range(n_bodies)),
            spinning_friction=float(values["spinning_friction"]),
            rolling_friction=float(values["rolling_friction"]),
            contact_stiffness=stiffness if compliant else None,
            contact_damping=float(values["contact_damping_ratio"]) * stiffness * TABLE_2A.dt if compliant else None,
        )

    def to_values(self, parameters: BulletParameters) -> dict[str, float]:
        values = {f"object_friction_{k}": f for k, f in enumerate(parameters.object_friction)}
        values |= {f"restitution_{k}": r for k, r in enumerate(parameters.restitution)}
        values |= {"spinning_friction": parameters.spinning_friction, "rolling_friction": parameters.rolling_friction}
        if parameters.contact_stiffness is None:  # rigid: the compliant entries do not act, at their search start
            unused = {d.name: d.init for d in self.dimensions(0) if d.when == ("contact", "compliant")}
            return values | {"contact": 0.0} | unused
        ratio = parameters.contact_damping / (parameters.contact_stiffness * TABLE_2A.dt)
        return values | {
            "contact": 1.0,
            "contact_stiffness": parameters.contact_stiffness,
            "contact_damping_ratio": ratio,
        }

    def rollouts(self, scene: Scene, nthread: int | None = None, substeps: int = 1) -> SteppedRollouts:
        return SteppedRollouts(scene, BulletWorld, nthread, substeps)

    def scene_files(self, scene: Scene, parameters: BulletParameters, substeps: int = 1) -> dict[str, str]:
        return scene_files(scene, parameters)
