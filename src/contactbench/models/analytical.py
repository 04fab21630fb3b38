"""MuJoCo with fixed contact parameters: its own defaults (untuned) or a named published preset."""

from __future__ import annotations

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.models.base import ContactModel
from contactbench.protocol import Context
from contactbench.recordings import Scene
from contactbench.sim.mujoco_scene import ContactParameters, scene_xml
from contactbench.sim.rollout import rollout_context

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


class MujocoContactModel(ContactModel):
    """Rolls MuJoCo out from the context with the given contact parameters (nothing is fitted)."""

    def __init__(
        self, name: str, preset: str | None = None, parameters: ContactParameters | None = None, substeps: int = 1
    ):
        if (preset is None) == (parameters is None):
            raise ValueError("give exactly one of preset or parameters")
        self.name = name
        self.preset = preset
        self.parameters = parameters
        self.substeps = substeps

    def contact_parameters(self, dataset: Scene) -> ContactParameters:
        return self.parameters if self.parameters is not None else preset_parameters(self.preset, dataset.n_bodies)

    def scene_xml(self, dataset: Scene) -> str:
        return scene_xml(dataset, self.contact_parameters(dataset), self.substeps)

    def rollout(self, scene: Scene, context: Context) -> np.ndarray:
        return rollout_context(scene, context, self.contact_parameters(scene), substeps=self.substeps)
