"""MuJoCo behind the engine interface: Table 2c's parameters, batched native rollouts, the scene as MJCF."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

from contactbench.scene import Scene
from contactbench.sim.effects import EFFECT_NAMES, SceneEffects
from contactbench.sim.engines import Dimension, Engine
from contactbench.sim.mujoco_scene import ContactParameters, scene_xml
from contactbench.sim.rollout import MujocoRollouts

# Table 2c: per-object and floor friction, the floor's direct solref stiffness (log scale) and damping. The damping
# search starts at 50: the domain's centre (500) diverges at the datasets' dt (~6.8 ms), where damping x dt ~ 1.
FRICTION = (0.0, 1.0)
STIFFNESS = (1e2, 1e4)
DAMPING = (0.0, 1e3)
INITIAL_DAMPING = 50.0


class MujocoEngine(Engine):
    """MuJoCo 3 (soft convex contact, semi-implicit Euler), rolled out by mujoco.rollout over threads."""

    name = "mujoco"

    def library_effects(self, scene: Scene) -> frozenset[str]:
        return frozenset(EFFECT_NAMES)

    def with_effects(
        self,
        parameters: ContactParameters,
        effects: SceneEffects,
        rolling_friction: float = 0.0,
        torsional_friction: float = 0.0,
    ) -> ContactParameters:
        return replace(
            parameters, effects=effects, rolling_friction=rolling_friction, torsional_friction=torsional_friction
        )

    def default_parameters(self, n_bodies: int) -> ContactParameters:
        return ContactParameters.mujoco_default(n_bodies)

    def dimensions(self, n_bodies: int) -> tuple[Dimension, ...]:
        return (
            *(Dimension(f"object_friction_{k}", *FRICTION) for k in range(n_bodies)),
            Dimension("floor_friction", *FRICTION),
            Dimension("floor_stiffness", *STIFFNESS, log=True),
            Dimension("floor_damping", *DAMPING, init=INITIAL_DAMPING),
        )

    def from_values(self, values: Mapping[str, float], n_bodies: int) -> ContactParameters:
        return ContactParameters(
            object_friction=tuple(float(values[f"object_friction_{k}"]) for k in range(n_bodies)),
            floor_friction=float(values["floor_friction"]),
            floor_stiffness=float(values["floor_stiffness"]),
            floor_damping=float(values["floor_damping"]),
        )

    def to_values(self, parameters: ContactParameters) -> dict[str, float]:
        values = {f"object_friction_{k}": f for k, f in enumerate(parameters.object_friction)}
        return values | {
            "floor_friction": parameters.floor_friction,
            "floor_stiffness": parameters.floor_stiffness,
            "floor_damping": parameters.floor_damping,
        }

    def rollouts(self, scene: Scene, nthread: int | None = None, substeps: int = 1) -> MujocoRollouts:
        return MujocoRollouts(scene, nthread, substeps)

    def scene_files(self, scene: Scene, parameters: ContactParameters, substeps: int = 1) -> dict[str, str]:
        return {"scene.xml": scene_xml(scene, parameters, substeps)}
