"""The simulators a contact model can be identified in: one interface (parameters, batched rollouts, scene file)."""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.scene import Scene
from contactbench.sim.effects import SceneEffects

# Engine name -> the class implementing it, imported on first use (Drake is a large import).
ENGINE_CLASSES = {
    "mujoco": "contactbench.sim.mujoco_engine:MujocoEngine",
    "bullet": "contactbench.sim.bullet_engine:BulletEngine",
    "drake": "contactbench.sim.drake_engine:DrakeEngine",
}
# Engine name -> the package a generator names in a dataset's meta.generator.engine.
ENGINE_PACKAGES = {"mujoco": "mujoco", "bullet": "pybullet", "drake": "drake"}


@dataclass(frozen=True)
class Dimension:
    """One identified parameter: its name, its range, whether it is searched on a log scale, and where a search
    starts (None: the middle of the range). With `choices` it is discrete instead: its value is the index of one
    of them (low and high are then 0 and the last index). With `when` = (discrete dimension, choice) it acts only
    where that dimension takes that choice, and stays at `init` elsewhere."""

    name: str
    low: float = 0.0
    high: float = 1.0
    log: bool = False
    init: float | None = None
    choices: tuple[str, ...] = ()
    when: tuple[str, str] | None = None

    def __post_init__(self):
        if self.choices:
            object.__setattr__(self, "low", 0.0)
            object.__setattr__(self, "high", float(len(self.choices) - 1))
        elif not (self.low < self.high) or (self.log and self.low <= 0):
            raise ContactbenchError(
                f"parameter {self.name!r}: range [{self.low}, {self.high}] is empty or, on a log scale, not positive"
            )


class Engine(ABC):
    """What identification and the fixed-parameter models need of a simulator; each engine's parameters are a frozen
    (hashable) dataclass of its own."""

    name: str

    @abstractmethod
    def default_parameters(self, n_bodies: int) -> Any:
        """The engine's own defaults: the untuned simulation."""

    @abstractmethod
    def dimensions(self, n_bodies: int) -> tuple[Dimension, ...]:
        """The parameters identification searches, with their ranges."""

    @abstractmethod
    def from_values(self, values: Mapping[str, float], n_bodies: int) -> Any:
        """Parameters from {dimension name: value} (every dimension given)."""

    @abstractmethod
    def to_values(self, parameters: Any) -> dict[str, float]:
        """{dimension name: value} of parameters (the inverse of from_values)."""

    def library_effects(self, scene: Scene) -> frozenset[str]:
        """The diagnosis library's effects (sim.effects.EFFECT_NAMES) this engine models in the scene."""
        return frozenset()

    def with_effects(
        self, parameters: Any, effects: SceneEffects, rolling_friction: float = 0.0, torsional_friction: float = 0.0
    ) -> Any:
        """`parameters` with the diagnosis' effects switched on (only those of library_effects may be set)."""
        raise NotApplicable(f"the {self.name} engine models none of the diagnosis' effects")

    def check_scene(self, scene: Scene) -> None:  # noqa: B027 (engines that take every scene check nothing)
        """Raise NotApplicable (one line: the job is skipped, not failed) for a scene this engine cannot simulate."""

    @abstractmethod
    def rollouts(self, scene: Scene, nthread: int | None = None, substeps: int = 1):
        """A `contactbench.sim.rollout.Rollouts` of the scene: batched simulation of many parameter sets x tosses."""

    @abstractmethod
    def scene_files(self, scene: Scene, parameters: Any, substeps: int = 1) -> dict[str, str]:
        """The scene with these parameters in the engine's own format, to open in its tools: {relative path: text},
        the scene file first, then the mesh files it references."""


def engine(name: str) -> Engine:
    """The engine registered under `name` (ENGINE_CLASSES)."""
    if name not in ENGINE_CLASSES:
        raise ContactbenchError(f"unknown engine {name!r} (expected one of {', '.join(ENGINE_CLASSES)})")
    module, _, attribute = ENGINE_CLASSES[name].partition(":")
    return getattr(importlib.import_module(module), attribute)()


def made_by(engine_name: str | None, meta: Mapping) -> bool:
    """Whether the engine `engine_name` (None: no engine) generated the data whose meta.json is `meta`."""
    generator = meta.get("generator")
    made = generator.get("engine") if isinstance(generator, Mapping) else None
    return engine_name is not None and made is not None and ENGINE_PACKAGES.get(engine_name) == made


def require_flat(scene: Scene, engine_name: str) -> None:
    """NotApplicable for scenes beyond free convex-collided bodies on the flat floor (recordings version 2's pieces,
    terrain and joints), which only MuJoCo's scene builder writes so far."""
    if not scene.flat:
        raise NotApplicable(
            f"the {engine_name} engine simulates free convex bodies on the flat floor; {scene.name} has non-convex "
            "bodies, terrain or joints (model=sysid and mujoco_default simulate those)"
        )
