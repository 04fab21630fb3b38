"""Physics beyond an engine's contact parameters that a diagnosis may switch on in any engine that models it
(Engine.library_effects): what each one is, in the recordings' terms, and the bodies' inertial frames with them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.scene import Scene
from contactbench.values import freeze_numbers

# The diagnosis library's effects by name (Engine.library_effects answers in them): each is a SceneEffects field an
# engine may model, and a switch the generator can turn on in PyBullet without telling (generation/effects.py).
EFFECT_NAMES = (
    "air_drag",
    "wind",
    "rolling_friction",
    "torsional_friction",
    "anisotropic_friction",
    "com_offset",
    "inertia_mismatch",
    "floor_offset",
    "floor_tilt",
    "gravity_scale",
)


@dataclass(frozen=True)
class SceneEffects:
    """Physics outside Table 2c, each off by default; diagnose.py switches them on when recordings ask for it."""

    fluid_density: float = 0.0  # kg/m^3: MuJoCo's inertia-box fluid model (quadratic drag on every body)
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m/s, world frame; acts through fluid_density only
    friction_anisotropy: float = 1.0  # floor friction along world x / along world y (their geometric mean is fixed)
    com_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, body frame, added to every body's centre of mass
    inertia_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)  # multiplies every body's inertia along the mesh axes
    floor_offset: float = 0.0  # m, the floor's height above the recordings' floor_z
    floor_tilt: tuple[float, float] = (0.0, 0.0)  # rad, the floor's rotation about world x, then about world y
    # The simulated gravity / the recordings' meta.gravity: with the recorded velocities as initial states this is
    # exactly a tracker time base off by sqrt(gravity_scale) (contact stiffness and damping are fitted anyway).
    gravity_scale: float = 1.0

    def __post_init__(self):
        freeze_numbers(self, vectors=("wind", "com_offset", "inertia_scale", "floor_tilt"))
        if not (
            self.fluid_density >= 0
            and self.friction_anisotropy > 0
            and min(self.inertia_scale) > 0
            and self.gravity_scale > 0
        ):
            raise ContactbenchError(
                f"fluid density must be >= 0, friction anisotropy, inertia and gravity scales > 0, got {self}"
            )


NO_EFFECTS = SceneEffects()


def inertials(dataset: Scene, effects: SceneEffects = NO_EFFECTS) -> tuple[np.ndarray, np.ndarray]:
    """Every body's centre of mass [K, 3] (mesh frame) and inertia tensor about it [K, 3, 3] in the scene with
    `effects` (an offset centre of mass, scaled inertias)."""
    root_scale = np.sqrt(np.array(effects.inertia_scale))
    properties = [dataset.inertial(k) for k in range(dataset.n_bodies)]
    coms = np.stack([com + np.array(effects.com_offset) for com, _ in properties])
    return coms, np.stack([root_scale[:, None] * inertia * root_scale[None, :] for _, inertia in properties])


def inertial_frames(scene: Scene, effects: SceneEffects = NO_EFFECTS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per body: centre of mass [K, 3] and principal axes [K, 4] (w-first) in the mesh frame, principal moments [K, 3],
    with `effects`' offset centre of mass and scaled inertia.

    Within 1e-9 of the origin and of diagonal (a generated scene's mesh frame) they are taken as exactly so, so that a
    generated dataset's world is the generator's to the last bit."""
    coms, axes, moments = [], [], []
    centres, inertias = inertials(scene, effects)
    for k in range(scene.n_bodies):
        com, inertia = centres[k], inertias[k]
        width = scene.body_mesh(k).width
        com = np.where(np.abs(com) > 1e-9 * width, com, 0.0)
        if np.abs(inertia - np.diag(np.diag(inertia))).max() <= 1e-9 * np.trace(inertia):
            principal, rotation = np.diag(inertia).copy(), np.eye(3)
        else:
            principal, rotation = np.linalg.eigh(inertia)
            rotation[:, 2] *= np.linalg.det(rotation)  # a proper rotation
        coms.append(com)
        axes.append(rotations.from_matrix(rotation))
        moments.append(principal)
    return np.array(coms), np.array(axes), np.array(moments)


class InertiaBoxDrag:
    """MuJoCo's inertia-box fluid model in moving air, for engines that apply it as a force and torque each step: on
    each body's box (its principal frame, the sides s of the uniform box with its principal moments), a force
    -rho/2 s_j s_k |u_i| u_i along each axis i, u the centre of mass's velocity against the wind, and a torque
    -rho s_i (s_j^4 + s_k^4) / 64 |w_i| w_i."""

    def __init__(self, scene: Scene, effects: SceneEffects, moments: np.ndarray):
        self.density, self.wind = effects.fluid_density, np.asarray(effects.wind, dtype=np.float64)
        masses = np.array([body.mass for body in scene.bodies])
        sides = np.sqrt(np.maximum(6.0 * (moments.sum(axis=1, keepdims=True) - 2.0 * moments) / masses[:, None], 0.0))
        fourth = sides**4
        self.areas = np.stack([sides[:, 1] * sides[:, 2], sides[:, 0] * sides[:, 2], sides[:, 0] * sides[:, 1]], 1)
        self.spin_drag = (
            sides
            * np.stack([fourth[:, 1] + fourth[:, 2], fourth[:, 0] + fourth[:, 2], fourth[:, 0] + fourth[:, 1]], 1)
            / 64.0
        )

    def wrenches(self, principal: np.ndarray, linear: np.ndarray, spin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World force and torque [K, 3] each, for principal frames in the world [K, 3, 3] and each centre of mass's
        world velocity and spin [K, 3]."""
        local = np.einsum("kji,kj->ki", principal, linear - self.wind)
        turning = np.einsum("kji,kj->ki", principal, spin)
        force = -0.5 * self.density * self.areas * np.abs(local) * local
        torque = -self.density * self.spin_drag * np.abs(turning) * turning
        return np.einsum("kij,kj->ki", principal, force), np.einsum("kij,kj->ki", principal, torque)
