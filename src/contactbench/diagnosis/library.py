"""The candidate effects and the base parameters as one vector of fit parameters, mapped to MuJoCo's model."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.generation.effects import EFFECT_NAMES
from contactbench.sim.mujoco_scene import ContactParameters, SceneEffects


@dataclass(frozen=True)
class Parameter:
    name: str  # as reported; a "log" parameter is fitted as the logarithm of this value
    lower: float  # bounds of the fitted (internal) value
    upper: float
    start: float  # internal value a fit starts from; for an effect, the value that switches it off (but see wind)
    log: bool = False

    def reported(self, internal: float) -> float:
        return float(np.exp(internal)) if self.log else float(internal)


@dataclass(frozen=True)
class Effect:
    name: str
    parameters: tuple[Parameter, ...]
    physics: str  # what it is, in words (for the report)
    mujoco: str  # how it is modelled in MuJoCo
    # A model-free measurement (free flight) shows this effect beyond its own practical margin on val: the effect
    # then counts as practically meaningful without closing the simulator-loss margin (it must still be significant).
    measured: bool = False
    # The smallest fitted size that is this physics, where switching the effect on changes MuJoCo's contact model
    # itself (condim 4 or 6): below it, what improves the fit is the switch, not the friction (a rhombicuboctahedron
    # null "improved" 5% with torsional friction 5e-5 m). 0: every non-zero value counts.
    resolution: float = 0.0

    def negligible(self, reported: dict[str, float]) -> bool:
        """Whether fitted values (reported units) all lie within `resolution` of the values that switch it off."""
        return self.resolution > 0 and all(
            abs(reported[p.name] - p.reported(p.start)) < self.resolution for p in self.parameters
        )


# Rolling and torsional friction at 0.005 m went unnoticed in the first blind proof; a fit under 1 mm is the switch.
CONTACT_DIMENSION_RESOLUTION = 1e-3  # m


GRAVITY_SCALE_BOUNDS = (0.8, 1.2)


def library(width: float, gravity_scale: float = 1.0, gravity_measured: bool = False) -> dict[str, Effect]:
    """The candidate effects for bodies of the given width (m); their names are generation.effects.EFFECT_NAMES.
    `gravity_scale`: where the gravity_scale fit starts, the train split's free-flight measurement (1: off);
    `gravity_measured`: the free-flight check found an apparent gravity on val (diagnosis.free_flight)."""
    reach = 0.3 * width
    gravity_start = float(np.clip(gravity_scale, *GRAVITY_SCALE_BOUNDS))
    effects = [
        Effect(
            "air_drag",
            (Parameter("fluid_density", 0.0, 600.0, 0.0),),
            "quadratic air drag",
            "option density (inertia-box fluid model)",
        ),
        # Wind only acts through the fluid, so its fit starts with some fluid present (else it has no gradient).
        Effect(
            "wind",
            (
                Parameter("fluid_density", 0.0, 600.0, 30.0),
                Parameter("wind_x", -5.0, 5.0, 0.0),
                Parameter("wind_y", -5.0, 5.0, 0.0),
            ),
            "a steady wind",
            "option density + wind",
        ),
        Effect(
            "rolling_friction",
            (Parameter("rolling_friction", 0.0, 0.05, 0.0),),
            "rolling resistance",
            "condim 6, rolling friction",
            resolution=CONTACT_DIMENSION_RESOLUTION,
        ),
        Effect(
            "torsional_friction",
            (Parameter("torsional_friction", 0.0, 0.05, 0.0),),
            "torsional (spin) friction",
            "condim 4, torsional friction",
            resolution=CONTACT_DIMENSION_RESOLUTION,
        ),
        Effect(
            "anisotropic_friction",
            (Parameter("friction_anisotropy", -2.0, 2.0, 0.0, log=True),),
            "floor friction that differs between directions",
            "contact pair friction, x vs y tangent",
        ),
        Effect(
            "com_offset",
            tuple(Parameter(f"com_offset_{axis}", -reach, reach, 0.0) for axis in "xyz"),
            "a centre of mass away from the mesh's centroid",
            "body inertial pos",
        ),
        Effect(
            "inertia_mismatch",
            tuple(Parameter(f"inertia_scale_{axis}", -0.7, 0.7, 0.0, log=True) for axis in "xyz"),
            "an inertia other than the uniform-density mesh's",
            "body fullinertia",
        ),
        Effect(
            "floor_offset",
            (Parameter("floor_offset", -reach, reach, 0.0),),
            "a floor higher or lower than recorded",
            "floor geom pos",
        ),
        Effect(
            "floor_tilt",
            (Parameter("floor_tilt_x", -0.15, 0.15, 0.0), Parameter("floor_tilt_y", -0.15, 0.15, 0.0)),
            "a tilted floor",
            "floor geom quat",
        ),
        # Free flight shows it first (diagnosis.free_flight); modelled as MuJoCo's gravity, it also carries what a
        # time base off by sqrt(scale) does to contact (friction and impacts play out in the same scaled time). Its fit
        # starts from the free-flight measurement on train: the short-horizon loss is dominated by impacts, whose
        # squared residuals hide the small, steady free-flight signal from the screen's Gauss-Newton step.
        Effect(
            "gravity_scale",
            (Parameter("gravity_scale", *GRAVITY_SCALE_BOUNDS, gravity_start),),
            "an apparent gravity other than meta.gravity: the tracker's time base (true frame interval sqrt(scale) dt) "
            "or length scale off, or meta.gravity wrong",
            "option gravity x scale",
            measured=gravity_measured,
        ),
    ]
    assert tuple(effect.name for effect in effects) == EFFECT_NAMES
    return {effect.name: effect for effect in effects}


def base_parameters(n_bodies: int) -> tuple[Parameter, ...]:
    """Table 2c: object friction per body, floor stiffness (log), floor damping. The floor's own friction stays 0,
    so a floor contact's friction (MuJoCo takes the larger of the two) is the object's."""
    return (
        *(Parameter(f"object_friction_{k}", 0.0, 1.0, 0.5) for k in range(n_bodies)),
        Parameter("floor_stiffness", float(np.log(1e2)), float(np.log(1e4)), float(np.log(1e3)), log=True),
        Parameter("floor_damping", 0.0, 1e3, 50.0),
    )


@dataclass(frozen=True)
class Hypothesis:
    """The base simulator plus some named effects: its fit parameters and how they become MuJoCo's."""

    n_bodies: int
    effects: tuple[Effect, ...] = ()

    @property
    def parameters(self) -> tuple[Parameter, ...]:
        return base_parameters(self.n_bodies) + tuple(p for effect in self.effects for p in effect.parameters)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(effect.name for effect in self.effects)

    def with_effect(self, effect: Effect) -> Hypothesis:
        return dataclasses.replace(self, effects=self.effects + (effect,))

    def start(self, previous: Hypothesis | None = None, values: np.ndarray | None = None) -> np.ndarray:
        """Internal start vector: a previous hypothesis' fitted values where parameters are shared, else defaults."""
        known = dict(zip(previous.keys(), values)) if previous is not None else {}
        return np.array([known.get(key, p.start) for key, p in zip(self.keys(), self.parameters)])

    def keys(self) -> list[str]:
        """Unique keys: an effect's parameter is keyed by effect and name (wind and air_drag both have a density)."""
        n_base = len(base_parameters(self.n_bodies))
        keys = [p.name for p in self.parameters[:n_base]]
        return keys + [f"{effect.name}.{p.name}" for effect in self.effects for p in effect.parameters]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([p.lower for p in self.parameters]), np.array([p.upper for p in self.parameters])

    def reported(self, values: np.ndarray) -> dict[str, dict[str, float]]:
        """{"base": {...}, effect name: {...}} in reported units."""
        named = [(key, p.reported(v)) for key, p, v in zip(self.keys(), self.parameters, values)]
        out: dict[str, dict[str, float]] = {"base": {}}
        for key, value in named:
            group, _, name = key.rpartition(".")
            out.setdefault(group or "base", {})[name] = value
        return out

    def contact_parameters(self, values: np.ndarray) -> ContactParameters:
        """MuJoCo's parameters for internal values (within bounds)."""
        reported = self.reported(np.asarray(values, dtype=float))
        base = reported.pop("base")
        scene: dict[str, object] = {}
        extra: dict[str, float] = {}
        for name, values_of in reported.items():
            if name in ("air_drag", "wind"):
                scene["fluid_density"] = scene.get("fluid_density", 0.0) + values_of["fluid_density"]
                if name == "wind":
                    scene["wind"] = (values_of["wind_x"], values_of["wind_y"], 0.0)
            elif name in ("rolling_friction", "torsional_friction"):
                extra[name] = values_of[name]
            elif name == "anisotropic_friction":
                scene["friction_anisotropy"] = values_of["friction_anisotropy"]
            elif name == "com_offset":
                scene["com_offset"] = tuple(values_of[f"com_offset_{a}"] for a in "xyz")
            elif name == "inertia_mismatch":
                scene["inertia_scale"] = tuple(values_of[f"inertia_scale_{a}"] for a in "xyz")
            elif name == "floor_offset":
                scene["floor_offset"] = values_of["floor_offset"]
            elif name == "floor_tilt":
                scene["floor_tilt"] = (values_of["floor_tilt_x"], values_of["floor_tilt_y"])
            elif name == "gravity_scale":
                scene["gravity_scale"] = values_of["gravity_scale"]
            else:
                raise ContactbenchError(f"no MuJoCo model for effect {name!r}")
        return ContactParameters(
            object_friction=tuple(base[f"object_friction_{k}"] for k in range(self.n_bodies)),
            floor_friction=0.0,
            floor_stiffness=base["floor_stiffness"],
            floor_damping=base["floor_damping"],
            effects=SceneEffects(**scene),
            **extra,
        )
