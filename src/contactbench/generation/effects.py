"""Physics switched on in PyBullet and left out of the recordings' meta: hidden truths for testing diagnose.py."""

from __future__ import annotations

from dataclasses import dataclass

from contactbench.errors import ContactbenchError
from contactbench.sim.effects import EFFECT_NAMES
from contactbench.values import freeze_numbers

# Physics PyBullet can switch on that the diagnosis library does not list (no MuJoCo model of them there): they
# test whether diagnose.py says `unexplained` instead of a wrong name or `none`.
OUTSIDE_LIBRARY = ("coriolis", "floor_viscosity", "floor_centring", "spin_damping")
# Strength 1 of each effect. The tosses are short and slow (about 1 m/s, 0.15 s of flight, then sliding), so
# the fluid is dense: at 60 kg/m^3 drag decelerates a sliding cube by about 1 m/s^2 against friction's ~5.
# Rolling and spinning friction start at 0.01 m: at half that the first blind proof missed both (their short-horizon
# signal stayed under the margin although the held-out error rose; docs/results/calibration.md).
FLUID_DENSITY = 60.0  # kg/m^3


@dataclass(frozen=True)
class ConcealedEffects:
    """What PyBullet does beyond the recorded settings; every field at its default leaves PyBullet untouched."""

    fluid_density: float = 0.0  # kg/m^3: drag on each body by MuJoCo's inertia-box law (see bullet.BulletScene)
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m/s, world frame
    rolling_friction: float = 0.0  # PyBullet rollingFriction of every body (m)
    spinning_friction: float = 0.0  # PyBullet spinningFriction of every body (m)
    floor_friction_scale: tuple[float, float] = (1.0, 1.0)  # PyBullet anisotropicFriction of the floor along world x, y
    com_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, body frame: the true centre of mass minus the mesh's
    inertia_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)  # true inertia / the mesh's, along the mesh axes
    floor_offset: float = 0.0  # m, true floor height minus the recorded floor_z
    floor_tilt: tuple[float, float] = (0.0, 0.0)  # rad, the floor's rotation about world x, then about world y
    # PyBullet's gravity / the recorded meta.gravity: what a tracker whose time base or length scale is off shows
    # (the real ContactNets cube falls measurably short of g in free flight: docs/results/real_data.md).
    gravity_scale: float = 1.0
    # Outside the library (OUTSIDE_LIBRARY), each an acceleration of every body's centre of mass, or its spin:
    coriolis: float = 0.0  # rad/s: in any phase, -2 coriolis z x v: the recordings' frame turns about the vertical
    floor_viscosity: float = 0.0  # 1/s: while touching the floor, -floor_viscosity * (v_x, v_y): a viscous floor
    floor_centring: float = 0.0  # 1/s^2: while touching the floor, -floor_centring * (x, y): a floor bowl
    spin_damping: float = 0.0  # 1/s: in any phase a torque -spin_damping * I w: torque-free spin decays as exp(-rate t)

    def __post_init__(self):
        freeze_numbers(self, vectors=("wind", "floor_friction_scale", "com_offset", "inertia_scale", "floor_tilt"))

    @classmethod
    def named(cls, names, strength: float = 1.0) -> ConcealedEffects:
        """The effects `names` (from EFFECT_NAMES) at `strength` times their reference size."""
        unknown = [name for name in names if name not in EFFECT_NAMES + OUTSIDE_LIBRARY]
        if unknown:
            known = ", ".join(EFFECT_NAMES + OUTSIDE_LIBRARY)
            raise ContactbenchError(f"effects: unknown effect {unknown[0]!r}; known: {known}")
        if not strength > 0:
            raise ContactbenchError(f"effect_strength must be positive, got {strength}")
        s = float(strength)
        settings = {}
        for name in names:
            if name == "air_drag":
                settings["fluid_density"] = FLUID_DENSITY * s
            elif name == "wind":  # wind blows through a fluid: air_drag's if it is named too, else the reference one
                settings.setdefault("fluid_density", FLUID_DENSITY)
                settings["wind"] = (1.0 * s, 0.5 * s, 0.0)
            elif name == "rolling_friction":
                settings["rolling_friction"] = 0.01 * s
            elif name == "torsional_friction":
                settings["spinning_friction"] = 0.01 * s
            elif name == "anisotropic_friction":
                settings["floor_friction_scale"] = (1.0, 1.0 / (1.0 + 0.5 * s))
            elif name == "com_offset":
                settings["com_offset"] = (0.012 * s, -0.008 * s, 0.0)
            elif name == "inertia_mismatch":
                settings["inertia_scale"] = (1.0 + 0.25 * s, 1.0, 1.0 - 0.15 * s)
            elif name == "floor_offset":
                settings["floor_offset"] = 0.008 * s
            elif name == "floor_tilt":
                settings["floor_tilt"] = (0.025 * s, -0.012 * s)
            elif name == "gravity_scale":  # weaker, as the real cube's; 1 / (1 + 0.05 s) stays positive at any strength
                settings["gravity_scale"] = 1.0 / (1.0 + 0.05 * s)
            elif name == "coriolis":  # 1.5 m/s^2 sideways at 1 m/s
                settings["coriolis"] = 0.75 * s
            elif name == "floor_viscosity":  # 1.5 m/s^2 at 1 m/s of sliding, against friction's ~5
                settings["floor_viscosity"] = 1.5 * s
            elif name == "floor_centring":  # ~1 m/s^2 a fifth of a metre from the floor's origin
                settings["floor_centring"] = 5.0 * s
            elif name == "spin_damping":  # a cube spinning at 10 rad/s loses 3 rad/s over 0.15 s of flight
                settings["spin_damping"] = 2.0 * s
        return cls(**settings)

    def truth(self, names) -> list[dict]:
        """The hidden values in the diagnosis' parameter names (see contactbench.diagnosis.library)."""
        values = {
            "air_drag": {"fluid_density": self.fluid_density},
            "wind": {"fluid_density": self.fluid_density, "wind_x": self.wind[0], "wind_y": self.wind[1]},
            "rolling_friction": {"rolling_friction": self.rolling_friction},
            "torsional_friction": {"torsional_friction": self.spinning_friction},
            "anisotropic_friction": {
                "friction_anisotropy": self.floor_friction_scale[0] / self.floor_friction_scale[1]
            },
            "com_offset": dict(zip(("com_offset_x", "com_offset_y", "com_offset_z"), self.com_offset)),
            "inertia_mismatch": dict(
                zip(("inertia_scale_x", "inertia_scale_y", "inertia_scale_z"), self.inertia_scale)
            ),
            "floor_offset": {"floor_offset": self.floor_offset},
            "floor_tilt": {"floor_tilt_x": self.floor_tilt[0], "floor_tilt_y": self.floor_tilt[1]},
            "gravity_scale": {"gravity_scale": self.gravity_scale},
            "coriolis": {"coriolis": self.coriolis},
            "floor_viscosity": {"floor_viscosity": self.floor_viscosity},
            "floor_centring": {"floor_centring": self.floor_centring},
            "spin_damping": {"spin_damping": self.spin_damping},
        }
        return [{"name": name, "parameters": values[name]} for name in names]

    @property
    def applied_forces(self) -> bool:
        """Whether forces must be applied before every engine step (drag or an outside-library effect)."""
        return self.fluid_density > 0 or bool(
            self.coriolis or self.floor_viscosity or self.floor_centring or self.spin_damping
        )


NONE = ConcealedEffects()
