"""A simulator with fixed contact parameters: an engine's own defaults (untuned), a published preset, or fitted ones."""

from __future__ import annotations

from typing import Any

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.models.base import ContactModel
from contactbench.protocol import Context
from contactbench.scene import Scene
from contactbench.sim.engines import engine
from contactbench.sim.mujoco_scene import ContactParameters

# Per-object friction is shared by all bodies of a scene; stiffness/damping are MuJoCo's direct solref (-k -b).
PRESETS: dict[str, dict[str, float]] = {
    # Acosta et al. 2022, parameters identified for the real ContactNets cube (cube and floor alike).
    "acosta2022": {"object_friction": 0.212, "floor_friction": 0.212, "floor_stiffness": 838.3, "floor_damping": 68.8},
}


def preset_parameters(preset: str, n_bodies: int) -> ContactParameters:
    if preset == "mujoco_default":
        return ContactParameters.mujoco_default(n_bodies)
    if preset not in PRESETS:
        raise ContactbenchError(f"unknown preset {preset!r}; known: mujoco_default, {', '.join(sorted(PRESETS))}")
    values = dict(PRESETS[preset])
    return ContactParameters(object_friction=(values.pop("object_friction"),) * n_bodies, **values)


class EngineContactModel(ContactModel):
    """Rolls an engine (sim/engines.py) out from the context with given contact parameters, or the engine's own
    defaults (preset "default"); nothing is fitted."""

    def __init__(
        self, name: str, engine: str, preset: str | None = None, parameters: Any | None = None, substeps: int = 1
    ):
        if (preset is None) == (parameters is None):
            raise ValueError("give exactly one of preset or parameters")
        self.name = name
        self.engine = engine
        self.preset = preset
        self.parameters = parameters
        self.substeps = substeps

    def contact_parameters(self, dataset: Scene) -> Any:
        if self.parameters is not None:
            return self.parameters
        if self.preset != "default":
            raise ContactbenchError(f"engine {self.engine!r} has no preset {self.preset!r} (only 'default')")
        return engine(self.engine).default_parameters(dataset.n_bodies)

    def scene_files(self, dataset: Scene) -> dict[str, str]:
        return engine(self.engine).scene_files(dataset, self.contact_parameters(dataset), self.substeps)

    def rollout(self, scene: Scene, context: Context) -> np.ndarray:
        rollouts = engine(self.engine).rollouts(scene, substeps=self.substeps)
        try:
            return rollouts.rollout_context(context, self.contact_parameters(scene)).poses[0]
        finally:
            rollouts.close()


class MujocoContactModel(EngineContactModel):
    """MuJoCo with its own defaults (preset "mujoco_default"), a published preset (PRESETS) or given parameters."""

    def __init__(
        self, name: str, preset: str | None = None, parameters: ContactParameters | None = None, substeps: int = 1
    ):
        super().__init__(name, "mujoco", preset, parameters, substeps)

    def contact_parameters(self, dataset: Scene) -> ContactParameters:
        return self.parameters if self.parameters is not None else preset_parameters(self.preset, dataset.n_bodies)
