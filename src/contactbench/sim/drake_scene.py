"""A recordings scene in Drake's terms, what the plant (drake_plant.py, drake_engine.py) and the SDFormat
writer (drake_sdf.py) share: the contact parameters, the contact settings fixed for every scene and the bodies'
convex hulls.

Parameters and what they mean physically
----------------------------------------
* ``object_friction[k]``, ``floor_friction``: Coulomb coefficients of body k's and the floor's material. Drake
  combines two materials' coefficients per contact pair as μ = 2 μ1 μ2 / (μ1 + μ2) (its own rule, applied by Drake;
  both static and dynamic coefficients get the same value: the discrete solvers use the dynamic one only). As with
  MuJoCo's Table 2c parameters, identification searches the per-body and the floor coefficients; their combination
  is Drake's.
* ``point_stiffness`` (N/m): compliant point contact's spring, f_n = k x (1 + d ẋ) with penetration x.
* ``hunt_crossley_dissipation`` d (s/m): the Hunt–Crossley damping of the same law; the coefficient of
  restitution falls roughly as 1 / (1 + d v) with impact speed v.
* ``contact_model``: "point" (compliant point contact, what Acosta et al. 2022 tuned) or "hydroelastic", in which
  every body is compliant hydroelastic with ``hydroelastic_modulus`` (Pa) against a rigid hydroelastic floor
  (pressure field contact; bodies collide with each other compliant-compliant); friction and dissipation act as in
  point contact and ``point_stiffness`` is unused.

Drake combines the two geometries' stiffnesses in series, k = k1 k2 / (k1 + k2), and their dissipations weighted
by stiffness, d = k2/(k1+k2) d1 + k1/(k1+k2) d2 (moduli in place of stiffnesses for hydroelastic). So that the
identified numbers are a floor contact's own values, every body carries ``point_stiffness`` and
``hunt_crossley_dissipation`` and the floor carries FLOOR_POINT_STIFFNESS (1e15 N/m: a floor contact's stiffness is
the body's to a relative 1e-8 for k <= 1e7) and the same dissipation (so the weighted mean is exactly d); in
hydroelastic contact the floor is rigid, so a floor contact has the body's modulus and dissipation exactly. Contacts
between two bodies have stiffness k/2 (in series), dissipation d and the harmonic-mean friction of the two bodies.

Defaults
--------
DrakeEngine.default_parameters are what MultibodyPlant uses when a geometry has no proximity properties, from
``pydrake.geometry.DefaultProximityProperties()`` in drake 1.51.1 (drake/geometry/scene_graph_config.h): friction
0.5 (static and dynamic), point stiffness 1e6 N/m, Hunt–Crossley dissipation 50 s/m, hydroelastic modulus 1e7 Pa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.multibody.plant import DiscreteContactApproximation
from scipy.spatial import ConvexHull

from contactbench.errors import ContactbenchError
from contactbench.scene import Scene
from contactbench.sim.articulation import Articulation
from contactbench.sim.effects import NO_EFFECTS, SceneEffects
from contactbench.values import freeze_numbers

CONTACT_MODELS = ("point", "hydroelastic")
DISCRETE_CONTACT_APPROXIMATION = DiscreteContactApproximation.kTamsi
# m: the spheres marking hull vertices (SDFormat refuses radius 0); contact starts this far before a vertex touches.
VERTEX_RADIUS = 1e-9
FLOOR_POINT_STIFFNESS = 1e15  # N/m: in series with a body's k <= 1e7 it changes the pair's k by at most 1e-8
# Tessellation size of hydroelastic meshes; a Convex's pressure field is built from its hull whatever the hint, which
# only affects primitives (spheres, cylinders), so any value serves.
HYDROELASTIC_RESOLUTION_HINT = 0.01
# drake 1.51.1 geometry::DefaultProximityProperties (see the module docstring).
DRAKE_DEFAULT_FRICTION = 0.5
DRAKE_DEFAULT_POINT_STIFFNESS = 1e6
DRAKE_DEFAULT_DISSIPATION = 50.0
DRAKE_DEFAULT_HYDROELASTIC_MODULUS = 1e7


@dataclass(frozen=True)
class DrakeParameters:
    """Drake's contact parameters (see the module docstring for their meaning and how Drake combines them)."""

    object_friction: tuple[float, ...]  # Coulomb coefficient per body, in the recordings' body order
    floor_friction: float
    point_stiffness: float  # N/m, every body (floor contacts: exactly this)
    hunt_crossley_dissipation: float  # s/m
    contact_model: str = "point"  # "point" or "hydroelastic"
    hydroelastic_modulus: float = DRAKE_DEFAULT_HYDROELASTIC_MODULUS  # Pa, every body; hydroelastic contact only
    articulation: Articulation | None = None  # hinged scenes: joint damping, friction and inertia; None: as recorded
    effects: SceneEffects = NO_EFFECTS  # the diagnosis' effects Drake models (DrakeEngine.library_effects)

    def __post_init__(self):
        freeze_numbers(self, vectors=("object_friction",), skip=("contact_model", "articulation", "effects"))
        frictions = self.object_friction + (self.floor_friction,)
        if self.contact_model not in CONTACT_MODELS:
            raise ContactbenchError(f"Drake contact_model must be one of {CONTACT_MODELS}, got {self.contact_model!r}")
        if not (np.isfinite(frictions).all() and min(frictions, default=0.0) >= 0):
            raise ContactbenchError(f"Drake friction coefficients must be finite and non-negative, got {frictions}")
        if not 0 < self.point_stiffness < np.inf or not 0 < self.hydroelastic_modulus < np.inf:
            raise ContactbenchError(
                f"Drake point stiffness and hydroelastic modulus must be positive and finite, got "
                f"{self.point_stiffness} N/m and {self.hydroelastic_modulus} Pa"
            )
        if not 0 <= self.hunt_crossley_dissipation < np.inf:
            raise ContactbenchError(
                f"Drake Hunt-Crossley dissipation must be non-negative and finite, got {self.hunt_crossley_dissipation}"
            )


def hull_vertices(scene: Scene, k: int) -> np.ndarray:
    """The vertices [V, 3] of body k's convex hull, mesh frame."""
    vertices = scene.body_mesh(k).vertices
    return vertices[ConvexHull(vertices).vertices]


def box_extents(scene: Scene, k: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Centre and size of body k's hull if it is a box along its mesh axes, else None."""
    corners = hull_vertices(scene, k)
    low, high = corners.min(axis=0), corners.max(axis=0)
    tolerance = 1e-9 * scene.body_mesh(k).width
    on_corners = np.all(np.minimum(np.abs(corners - low), np.abs(corners - high)) <= tolerance)
    return ((low + high) / 2, high - low) if len(corners) == 8 and on_corners else None
