"""The candidate effects and the base parameters as one vector of fit parameters, mapped to the base engine's
parameters (the diagnosis' own MuJoCo base, or another engine's contact law: diagnosis.bases)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from contactbench.diagnosis.free_flight import INCONCLUSIVE, MARGIN, MEASURED, RULED_OUT
from contactbench.errors import ContactbenchError
from contactbench.sim.effects import EFFECT_NAMES, SceneEffects
from contactbench.sim.engines import engine
from contactbench.sim.mujoco_scene import MUJOCO_DEFAULT_SOLIMP, ContactParameters

if TYPE_CHECKING:
    from contactbench.diagnosis.bases import EngineBase


@dataclass(frozen=True)
class Parameter:
    name: str  # as reported; a "log" parameter is fitted as the logarithm of this value
    lower: float  # bounds of the fitted (internal) value
    upper: float
    start: float  # internal value a fit starts from; for an effect, the value that switches it off (else `off`)
    log: bool = False
    # The smallest departure from the switch-off value (reported units) that is this physics; 0: any (see Effect).
    resolution: float = 0.0
    off: float | None = None  # the switch-off value (reported units) where the fit starts elsewhere; else start's

    def switched_off(self) -> float:
        return self.reported(self.start) if self.off is None else self.off

    def reported(self, internal: float) -> float:
        return float(np.exp(internal)) if self.log else float(internal)


@dataclass(frozen=True)
class Effect:
    name: str
    parameters: tuple[Parameter, ...]
    physics: str  # what it is, in words (for the report)
    mujoco: str  # how it is modelled in MuJoCo
    # What a model-free measurement (free flight) says of it on val: MEASURED beyond its own practical margin (the
    # effect then counts as practically meaningful without closing the simulator-loss margin; it must still be
    # significant), RULED_OUT (whatever the simulator gains with it is something else), or INCONCLUSIVE (the rule
    # alone decides; every effect free flight cannot show).
    evidence: str = INCONCLUSIVE
    # It changes how a body flies with no contact: only then is a gain on free-flight segments evidence of it (a
    # contact effect "gains" there by refitting the other parameters alone).
    in_flight: bool = False

    @property
    def measured(self) -> bool:
        return self.evidence == MEASURED

    @property
    def ruled_out(self) -> bool:
        return self.evidence == RULED_OUT

    def negligible(self, reported: dict[str, float]) -> bool:
        """Whether the fitted values (reported units) of every parameter with a resolution lie within it of the value
        that switches the effect off: the effect is then not this physics, whatever the fit gained (see below)."""
        resolved = [p for p in self.parameters if p.resolution > 0]
        return bool(resolved) and all(abs(reported[p.name] - p.switched_off()) < p.resolution for p in resolved)


# Resolutions: below them a fitted effect is a knob for the contact's model-form error, not the physics it names.
# Lengths: MuJoCo's soft contacts sink about a millimetre at rest, so a floor or centre of mass moved by less is the
# contact's softness, and switching rolling or torsional friction on changes MuJoCo's contact itself (condim 6 or 4),
# so a tiny value "improves" a null. The cases that set them: docs/results/calibration.md.
LENGTH_RESOLUTION = 1e-3  # m
RATIO_RESOLUTION = 0.02  # inertia scales, friction anisotropy
ANGLE_RESOLUTION = 2e-3  # rad: a millimetre over the half metre a toss travels
# A wind under a tenth of the tosses' ~1 m/s is air drag fitted beside other base parameters (true drags were named
# wind at speeds far below it).
WIND_RESOLUTION = 0.1  # m/s
# gravity_scale: the free-flight check's margin (a null was once named at a gravity indistinguishable from 1 g: what
# "closed" the loss was the refit of the base parameters the candidate brought, not gravity)
GRAVITY_RESOLUTION = MARGIN

GRAVITY_SCALE_BOUNDS = (0.8, 1.2)


def library(
    width: float,
    gravity_scale: float = 1.0,
    gravity: str = INCONCLUSIVE,
    drag: str = INCONCLUSIVE,
    contact: dict[str, str] | None = None,
) -> dict[str, Effect]:
    """The candidate effects for bodies of the given width (m); their names are sim.effects.EFFECT_NAMES.
    `gravity_scale`: where the gravity_scale fit starts, the train split's free-flight measurement (1: off);
    `gravity` / `drag`: what the free-flight check says of an apparent gravity / a drag on val (diagnosis.free_flight:
    MEASURED, RULED_OUT, INCONCLUSIVE). A drag there is air_drag's or wind's (drag in moving air): both share its
    evidence, and wind must still beat air_drag (Diagnosis.require_more_than_special_cases). Ruled out, they gain on
    the simulator's loss only through contact (they close a few percent of the base loss on nulls).
    `contact`: what the model-free contact signatures say of anisotropic_friction, torsional_friction and
    rolling_friction (diagnosis.contact_signatures.measure's `evidence`; absent: INCONCLUSIVE)."""
    contact = contact or {}
    reach = 0.3 * width
    gravity_start = float(np.clip(gravity_scale, *GRAVITY_SCALE_BOUNDS))
    effects = [
        Effect(
            "air_drag",
            (Parameter("fluid_density", 0.0, 600.0, 0.0),),
            "quadratic air drag",
            "option density (inertia-box fluid model)",
            evidence=drag,
            in_flight=True,
        ),
        # Wind only acts through the fluid, so its fit starts with some fluid present (else it has no gradient).
        Effect(
            "wind",
            (
                Parameter("fluid_density", 0.0, 600.0, 30.0),
                Parameter("wind_x", -5.0, 5.0, 0.0, resolution=WIND_RESOLUTION),
                Parameter("wind_y", -5.0, 5.0, 0.0, resolution=WIND_RESOLUTION),
            ),
            "a steady wind",
            "option density + wind",
            evidence=drag,
            in_flight=True,
        ),
        Effect(
            "rolling_friction",
            (Parameter("rolling_friction", 0.0, 0.05, 0.0, resolution=LENGTH_RESOLUTION),),
            "rolling resistance",
            "condim 6, rolling friction",
            evidence=contact.get("rolling_friction", INCONCLUSIVE),
        ),
        Effect(
            "torsional_friction",
            (Parameter("torsional_friction", 0.0, 0.05, 0.0, resolution=LENGTH_RESOLUTION),),
            "torsional (spin) friction",
            "condim 4, torsional friction",
            evidence=contact.get("torsional_friction", INCONCLUSIVE),
        ),
        Effect(
            "anisotropic_friction",
            (Parameter("friction_anisotropy", -2.0, 2.0, 0.0, log=True, resolution=RATIO_RESOLUTION),),
            "floor friction that differs between directions",
            "contact pair friction, x vs y tangent",
            evidence=contact.get("anisotropic_friction", INCONCLUSIVE),
        ),
        Effect(
            "com_offset",
            tuple(Parameter(f"com_offset_{axis}", -reach, reach, 0.0, resolution=LENGTH_RESOLUTION) for axis in "xyz"),
            "a centre of mass away from the mesh's centroid",
            "body inertial pos",
            in_flight=True,
        ),
        Effect(
            "inertia_mismatch",
            tuple(
                Parameter(f"inertia_scale_{axis}", -0.7, 0.7, 0.0, log=True, resolution=RATIO_RESOLUTION)
                for axis in "xyz"
            ),
            "an inertia other than the uniform-density mesh's",
            "body fullinertia",
            in_flight=True,
        ),
        Effect(
            "floor_offset",
            (Parameter("floor_offset", -reach, reach, 0.0, resolution=LENGTH_RESOLUTION),),
            "a floor higher or lower than recorded",
            "floor geom pos",
        ),
        Effect(
            "floor_tilt",
            (
                Parameter("floor_tilt_x", -0.15, 0.15, 0.0, resolution=ANGLE_RESOLUTION),
                Parameter("floor_tilt_y", -0.15, 0.15, 0.0, resolution=ANGLE_RESOLUTION),
            ),
            "a tilted floor",
            "floor geom quat",
        ),
        # Free flight shows it first (diagnosis.free_flight); modelled as MuJoCo's gravity, it also carries what a
        # time base off by sqrt(scale) does to contact (friction and impacts play out in the same scaled time). Its fit
        # starts from the free-flight measurement on train: the short-horizon loss is dominated by impacts, whose
        # squared residuals hide the small, steady free-flight signal from the screen's Gauss-Newton step.
        Effect(
            "gravity_scale",
            (Parameter("gravity_scale", *GRAVITY_SCALE_BOUNDS, gravity_start, resolution=GRAVITY_RESOLUTION, off=1.0),),
            "an apparent gravity other than meta.gravity: the tracker's time base (true frame interval sqrt(scale) dt) "
            "or length scale off, or meta.gravity wrong",
            "option gravity x scale",
            evidence=gravity,
            in_flight=True,
        ),
    ]
    assert tuple(effect.name for effect in effects) == EFFECT_NAMES
    return {effect.name: effect for effect in effects}


def base_parameters(n_bodies: int) -> tuple[Parameter, ...]:
    """Table 2c: object friction per body, floor stiffness (log), floor damping; and the floor contacts' impedance
    (MuJoCo's solimp dmin, dmax, width, starting at MuJoCo's defaults), which shapes an impact beyond stiffness and
    damping: contact model-form error left in the base is what spurious candidates ride on (on a null dodecahedron it
    closed a significant share of the base's val loss and of its test full-rollout error; on null cubes and tetrahedra
    nothing: docs/results/calibration.md). The floor's own friction stays 0, so a floor contact's friction (MuJoCo takes
    the larger of the two) is the object's."""
    return (
        *(Parameter(f"object_friction_{k}", 0.0, 1.0, 0.5) for k in range(n_bodies)),
        Parameter("floor_stiffness", float(np.log(1e2)), float(np.log(1e4)), float(np.log(1e3)), log=True),
        Parameter("floor_damping", 0.0, 1e3, 50.0),
        Parameter("floor_impedance_min", 0.3, 0.99, MUJOCO_DEFAULT_SOLIMP[0]),
        Parameter("floor_impedance_max", 0.5, 0.999, MUJOCO_DEFAULT_SOLIMP[1]),
        Parameter(
            "floor_impedance_width",
            float(np.log(1e-4)),
            float(np.log(0.05)),
            float(np.log(MUJOCO_DEFAULT_SOLIMP[2])),
            log=True,
        ),
    )


@dataclass(frozen=True)
class Hypothesis:
    """A base simulator plus some named effects: its fit parameters and how they become the engine's. The base is the
    diagnosis' own MuJoCo (base_parameters) unless `base` names another engine's contact law (diagnosis.bases)."""

    n_bodies: int
    effects: tuple[Effect, ...] = ()
    base: EngineBase | None = None

    @property
    def engine(self) -> str:
        return "mujoco" if self.base is None else self.base.engine

    @property
    def law(self) -> str:
        """The contact law it is fitted on, as the diagnosis labels laws: "mujoco", or the engine's base label."""
        return "mujoco" if self.base is None else self.base.label

    @property
    def base_fit_parameters(self) -> tuple[Parameter, ...]:
        return base_parameters(self.n_bodies) if self.base is None else self.base.parameters()

    @property
    def parameters(self) -> tuple[Parameter, ...]:
        return self.base_fit_parameters + tuple(p for effect in self.effects for p in effect.parameters)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(effect.name for effect in self.effects)

    def with_effect(self, effect: Effect) -> Hypothesis:
        return dataclasses.replace(self, effects=self.effects + (effect,))

    def with_effects(self, effects: tuple[Effect, ...]) -> Hypothesis:
        """The same base with exactly these effects."""
        return dataclasses.replace(self, effects=tuple(effects))

    def start(self, previous: Hypothesis | None = None, values: np.ndarray | None = None) -> np.ndarray:
        """Internal start vector: a previous hypothesis' fitted values where parameters are shared, else defaults."""
        known = dict(zip(previous.keys(), values)) if previous is not None else {}
        return np.array([known.get(key, p.start) for key, p in zip(self.keys(), self.parameters)])

    def keys(self) -> list[str]:
        """Unique keys: an effect's parameter is keyed by effect and name (wind and air_drag both have a density)."""
        keys = [p.name for p in self.base_fit_parameters]
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

    def contact_parameters(self, values: np.ndarray) -> Any:
        """The engine's parameters for internal values (within bounds)."""
        reported = self.reported(np.asarray(values, dtype=float))
        base = reported.pop("base")
        scene, extra = effect_settings(reported)
        if self.base is not None:
            parameters = self.base.engine_parameters(base)
            return (
                engine(self.engine).with_effects(parameters, SceneEffects(**scene), **extra) if reported else parameters
            )
        return ContactParameters(
            object_friction=tuple(base[f"object_friction_{k}"] for k in range(self.n_bodies)),
            floor_friction=0.0,
            floor_stiffness=base["floor_stiffness"],
            floor_damping=base["floor_damping"],
            floor_solimp=tuple(base[f"floor_impedance_{name}"] for name in ("min", "max", "width")),
            effects=SceneEffects(**scene),
            **extra,
        )


def effect_settings(reported: dict[str, dict[str, float]]) -> tuple[dict[str, object], dict[str, float]]:
    """The named effects' fitted values (reported units) as SceneEffects fields and the two friction extras (rolling
    and torsional friction), the same for every engine that models them."""
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
            raise ContactbenchError(f"no model for effect {name!r}")
    return scene, extra
