"""The blind proof of diagnose.py: library effects, effects outside the library, nulls, other shapes, no velocities.

Each case is generated with PyBullet (effects switched on there), copied with meta.generator stripped (and, for the
cases "without velocities", the recorded velocities too) under a neutral name, diagnosed through the same pipeline
as `python diagnose.py` (quick budget unless --budget), and only then scored against the hidden truth:

- a library effect: named, and nothing else (a different or an extra name is a wrong name);
- an effect outside the library (generation.effects.OUTSIDE_LIBRARY): verdict `unexplained`, located in a phase
  where that effect acts; any name is a wrong name;
- a null: verdict `none` (a name or `unexplained` is a false alarm).

The "tuning" cases are the ones the method was developed on; the "held_out" cases (other seeds, strengths and
shapes, no recorded velocities, two effects at once) were run to report, and then looked into; each later set
("held_out_2" ... "held_out_15": new seeds, shapes and strengths) was written before the diagnosis saw it, after the
changes its predecessor prompted, and run once. For named cases it also reports
the fraction of the excess held-out error closed, (base - augmented) / (base - base on the same tosses generated
without the effect). Prints the confusion matrix and a table; writes proof.json and proof.md under --out.

    python benchmarks/diagnosis_proof.py --set held_out_15     # one set (17-23 cases, 13-25 min on 2 cores)
    python benchmarks/diagnosis_proof.py --only floor_tilt      # the cases with floor_tilt
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from contactbench import atomic, runs
from contactbench.generation.effects import EFFECT_NAMES, OUTSIDE_LIBRARY
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.recordings import read_recordings, write_recordings

ROOT = Path(__file__).resolve().parents[1]
SHAPES = {
    "cube": SceneSpec(name="frictioncubes", friction=0.5, restitution=0.0),
    "dodecahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=12),
    "octahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=8),
    "icosahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=20),
    "tetrahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=4),
    "truncated_octahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=14),
    "rhombicuboctahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=26),
}
SETS = (
    "tuning",
    "held_out",
    "held_out_2",
    "held_out_3",
    "held_out_4",
    "held_out_5",
    "held_out_6",
    "held_out_7",
    "held_out_8",
    "held_out_9",
    "held_out_10",
    "held_out_11",
    "held_out_12",
    "held_out_13",
    "held_out_14",
    "held_out_15",
)
# Where each outside-library effect acts: an `unexplained` verdict must locate the mismatch in one of these phases.
ACTS_IN = {
    "coriolis": ("free", "sliding", "rolling"),
    "floor_viscosity": ("sliding", "rolling"),
    "floor_centring": ("sliding", "rolling", "rest"),
    "spin_damping": ("free", "sliding", "rolling"),
}


def case(shape, effects=(), strength=0.0, seed=0, velocities=True, kind="tuning") -> dict:
    return {
        "shape": shape,
        "effects": list(effects),
        "strength": strength,
        "seed": seed,
        "velocities": velocities,
        "set": kind,
    }


def cases() -> list[dict]:
    """Nulls first, so every effect case finds the null of its shape and seed."""
    tuning = [case("cube"), case("cube", seed=1), case("dodecahedron")]
    tuning += [case("cube", (e,), s) for e in EFFECT_NAMES for s in (1.0, 2.0)]
    tuning += [case("dodecahedron", (e,), 2.0) for e in ("air_drag", "floor_tilt")]
    tuning += [case("cube", (e,), 1.0) for e in OUTSIDE_LIBRARY]
    held = [
        case("cube", seed=5, velocities=False, kind="held_out"),
        case("octahedron", seed=5, kind="held_out"),
        case("cube", seed=5, kind="held_out"),
        case("cube", ("floor_offset",), 1.0, seed=5, velocities=False, kind="held_out"),
        case("cube", ("air_drag",), 1.5, seed=5, velocities=False, kind="held_out"),
        case("cube", ("rolling_friction",), 1.5, seed=5, velocities=False, kind="held_out"),
        case("octahedron", ("com_offset",), 2.0, seed=5, kind="held_out"),
        case("octahedron", ("floor_tilt",), 1.0, seed=5, kind="held_out"),
        case("cube", ("air_drag", "floor_tilt"), 1.5, seed=5, kind="held_out"),
        case("cube", ("coriolis",), 1.5, seed=5, velocities=False, kind="held_out"),
        case("cube", ("floor_viscosity",), 2.0, seed=5, kind="held_out"),
        case("octahedron", ("floor_centring",), 1.5, seed=5, kind="held_out"),
    ]
    # Written after the first held-out set had been seen (and the diagnosis changed because of it), run once: a new
    # seed, two shapes never diagnosed before, every library effect, two at once, outside effects, nulls.
    second = [
        case("cube", seed=7, kind="held_out_2"),
        case("icosahedron", seed=7, kind="held_out_2"),
        case("tetrahedron", seed=7, velocities=False, kind="held_out_2"),
        case("tetrahedron", ("air_drag",), 2.0, seed=7, kind="held_out_2"),
        case("icosahedron", ("wind",), 1.5, seed=7, velocities=False, kind="held_out_2"),
        case("cube", ("rolling_friction",), 2.0, seed=7, kind="held_out_2"),
        case("cube", ("torsional_friction",), 1.5, seed=7, velocities=False, kind="held_out_2"),
        case("icosahedron", ("anisotropic_friction",), 2.0, seed=7, kind="held_out_2"),
        case("cube", ("com_offset",), 1.5, seed=7, velocities=False, kind="held_out_2"),
        case("tetrahedron", ("inertia_mismatch",), 2.0, seed=7, kind="held_out_2"),
        case("icosahedron", ("floor_offset",), 1.5, seed=7, kind="held_out_2"),
        case("tetrahedron", ("floor_tilt",), 1.5, seed=7, velocities=False, kind="held_out_2"),
        case("icosahedron", ("gravity_scale",), 1.5, seed=7, kind="held_out_2"),
        case("cube", ("floor_offset", "com_offset"), 1.5, seed=7, kind="held_out_2"),
        case("tetrahedron", ("coriolis",), 1.0, seed=7, kind="held_out_2"),
        case("icosahedron", ("floor_viscosity",), 1.5, seed=7, velocities=False, kind="held_out_2"),
        case("cube", ("floor_centring",), 2.0, seed=7, velocities=False, kind="held_out_2"),
    ]
    # Written after held_out_2 had been seen (the open world's contact margin came from its tetrahedron null), run
    # once: a new seed, two shapes never diagnosed, four nulls (a tetrahedron again), every library effect, two at
    # once, seven cases without velocities, and a fourth outside effect the diagnosis was never developed on.
    third = [
        case("cube", seed=11, velocities=False, kind="held_out_3"),
        case("truncated_octahedron", seed=11, kind="held_out_3"),
        case("rhombicuboctahedron", seed=11, velocities=False, kind="held_out_3"),
        case("tetrahedron", seed=11, kind="held_out_3"),
        case("truncated_octahedron", ("air_drag",), 2.0, seed=11, velocities=False, kind="held_out_3"),
        case("rhombicuboctahedron", ("wind",), 1.5, seed=11, kind="held_out_3"),
        case("truncated_octahedron", ("rolling_friction",), 2.0, seed=11, kind="held_out_3"),
        case("cube", ("torsional_friction",), 2.0, seed=11, kind="held_out_3"),
        case("cube", ("anisotropic_friction",), 1.5, seed=11, velocities=False, kind="held_out_3"),
        case("rhombicuboctahedron", ("com_offset",), 2.0, seed=11, kind="held_out_3"),
        case("cube", ("inertia_mismatch",), 2.0, seed=11, velocities=False, kind="held_out_3"),
        case("tetrahedron", ("floor_offset",), 1.0, seed=11, kind="held_out_3"),
        case("truncated_octahedron", ("floor_tilt",), 1.5, seed=11, velocities=False, kind="held_out_3"),
        case("cube", ("gravity_scale",), 2.0, seed=11, kind="held_out_3"),
        case("cube", ("com_offset", "floor_tilt"), 1.5, seed=11, kind="held_out_3"),
        case("cube", ("spin_damping",), 1.0, seed=11, kind="held_out_3"),
        case("truncated_octahedron", ("coriolis",), 1.0, seed=11, velocities=False, kind="held_out_3"),
        case("cube", ("floor_viscosity",), 2.0, seed=11, kind="held_out_3"),
        case("rhombicuboctahedron", ("floor_centring",), 1.5, seed=11, velocities=False, kind="held_out_3"),
    ]
    # Written after held_out_3 had been seen (a rhombicuboctahedron null named torsional friction at 5e-5 m: the
    # contact-dimension resolution came from it), run once: seed 13, six nulls, the contact-dimension effects on new
    # shapes, every outside effect.
    fourth = [
        case("icosahedron", seed=13, velocities=False, kind="held_out_4"),
        case("rhombicuboctahedron", seed=13, kind="held_out_4"),
        case("dodecahedron", seed=13, velocities=False, kind="held_out_4"),
        case("tetrahedron", seed=13, velocities=False, kind="held_out_4"),
        case("cube", seed=13, kind="held_out_4"),
        case("octahedron", seed=13, kind="held_out_4"),
        case("rhombicuboctahedron", ("torsional_friction",), 1.5, seed=13, velocities=False, kind="held_out_4"),
        case("dodecahedron", ("rolling_friction",), 2.0, seed=13, kind="held_out_4"),
        case("octahedron", ("air_drag",), 1.5, seed=13, kind="held_out_4"),
        case("tetrahedron", ("wind",), 1.0, seed=13, velocities=False, kind="held_out_4"),
        case("icosahedron", ("com_offset",), 1.5, seed=13, kind="held_out_4"),
        case("dodecahedron", ("floor_tilt",), 1.0, seed=13, kind="held_out_4"),
        case("cube", ("floor_offset",), 1.5, seed=13, velocities=False, kind="held_out_4"),
        case("cube", ("spin_damping",), 2.0, seed=13, kind="held_out_4"),
        case("icosahedron", ("floor_viscosity",), 2.0, seed=13, kind="held_out_4"),
        case("dodecahedron", ("floor_centring",), 1.0, seed=13, velocities=False, kind="held_out_4"),
        case("cube", ("coriolis",), 0.75, seed=13, kind="held_out_4"),
    ]
    # Written after held_out_4 had been seen (an octahedron's air drag passed as a 1.5 cm/s wind: a general effect
    # must now beat its special case), run once: seed 17, drag and wind on four shapes, four nulls.
    fifth = [
        case("octahedron", seed=17, kind="held_out_5"),
        case("cube", seed=17, velocities=False, kind="held_out_5"),
        case("icosahedron", seed=17, kind="held_out_5"),
        case("truncated_octahedron", seed=17, velocities=False, kind="held_out_5"),
        case("octahedron", ("air_drag",), 1.5, seed=17, kind="held_out_5"),
        case("cube", ("air_drag",), 1.0, seed=17, velocities=False, kind="held_out_5"),
        case("icosahedron", ("air_drag",), 2.0, seed=17, kind="held_out_5"),
        case("icosahedron", ("wind",), 1.0, seed=17, kind="held_out_5"),
        case("truncated_octahedron", ("wind",), 1.5, seed=17, velocities=False, kind="held_out_5"),
        case("cube", ("torsional_friction",), 1.0, seed=17, kind="held_out_5"),
        case("icosahedron", ("rolling_friction",), 1.5, seed=17, velocities=False, kind="held_out_5"),
        case("octahedron", ("gravity_scale",), 2.0, seed=17, kind="held_out_5"),
        case("cube", ("inertia_mismatch",), 1.5, seed=17, kind="held_out_5"),
        case("truncated_octahedron", ("anisotropic_friction",), 2.0, seed=17, kind="held_out_5"),
        case("octahedron", ("floor_centring",), 1.5, seed=17, kind="held_out_5"),
        case("icosahedron", ("coriolis",), 1.0, seed=17, velocities=False, kind="held_out_5"),
        case("cube", ("floor_viscosity",), 1.5, seed=17, kind="held_out_5"),
        case("cube", ("spin_damping",), 3.0, seed=17, kind="held_out_5"),
    ]
    # Written after held_out_5 had been seen (drag named wind at 1 mm/s, drag with a 0.3 mm floor offset: every effect
    # now has a resolution), run once: seed 19, five nulls, every library effect, two at once, every outside effect.
    sixth = [
        case("cube", seed=19, kind="held_out_6"),
        case("octahedron", seed=19, velocities=False, kind="held_out_6"),
        case("icosahedron", seed=19, velocities=False, kind="held_out_6"),
        case("rhombicuboctahedron", seed=19, kind="held_out_6"),
        case("dodecahedron", seed=19, kind="held_out_6"),
        case("cube", ("air_drag",), 1.5, seed=19, velocities=False, kind="held_out_6"),
        case("dodecahedron", ("air_drag",), 2.0, seed=19, kind="held_out_6"),
        case("octahedron", ("wind",), 1.5, seed=19, kind="held_out_6"),
        case("icosahedron", ("torsional_friction",), 2.0, seed=19, kind="held_out_6"),
        case("cube", ("rolling_friction",), 2.0, seed=19, velocities=False, kind="held_out_6"),
        case("rhombicuboctahedron", ("anisotropic_friction",), 1.5, seed=19, kind="held_out_6"),
        case("octahedron", ("com_offset",), 1.5, seed=19, velocities=False, kind="held_out_6"),
        case("cube", ("inertia_mismatch",), 2.0, seed=19, kind="held_out_6"),
        case("icosahedron", ("floor_offset",), 1.5, seed=19, velocities=False, kind="held_out_6"),
        case("dodecahedron", ("floor_tilt",), 1.5, seed=19, kind="held_out_6"),
        case("octahedron", ("gravity_scale",), 2.0, seed=19, kind="held_out_6"),
        case("cube", ("air_drag", "floor_offset"), 1.5, seed=19, kind="held_out_6"),
        case("dodecahedron", ("coriolis",), 1.0, seed=19, kind="held_out_6"),
        case("octahedron", ("floor_centring",), 2.0, seed=19, velocities=False, kind="held_out_6"),
        case("rhombicuboctahedron", ("floor_viscosity",), 2.0, seed=19, kind="held_out_6"),
        case("icosahedron", ("spin_damping",), 3.0, seed=19, kind="held_out_6"),
    ]
    # Written after held_out_6 had been seen (effects at null values gaining on val by refitting the base: every
    # candidate is now judged against a refit control), run once: seed 23, five nulls, every library effect, two pairs,
    # every outside effect, tetrahedra and truncated octahedra back.
    seventh = [
        case("tetrahedron", seed=23, kind="held_out_7"),
        case("cube", seed=23, velocities=False, kind="held_out_7"),
        case("truncated_octahedron", seed=23, kind="held_out_7"),
        case("icosahedron", seed=23, kind="held_out_7"),
        case("rhombicuboctahedron", seed=23, velocities=False, kind="held_out_7"),
        case("tetrahedron", ("air_drag",), 2.0, seed=23, kind="held_out_7"),
        case("truncated_octahedron", ("wind",), 1.0, seed=23, velocities=False, kind="held_out_7"),
        case("cube", ("torsional_friction",), 1.5, seed=23, kind="held_out_7"),
        case("octahedron", ("rolling_friction",), 1.5, seed=23, kind="held_out_7"),
        case("cube", ("anisotropic_friction",), 2.0, seed=23, velocities=False, kind="held_out_7"),
        case("dodecahedron", ("com_offset",), 2.0, seed=23, kind="held_out_7"),
        case("truncated_octahedron", ("inertia_mismatch",), 2.0, seed=23, kind="held_out_7"),
        case("cube", ("floor_offset",), 1.0, seed=23, velocities=False, kind="held_out_7"),
        case("icosahedron", ("floor_tilt",), 1.5, seed=23, kind="held_out_7"),
        case("tetrahedron", ("gravity_scale",), 1.5, seed=23, velocities=False, kind="held_out_7"),
        case("octahedron", ("wind", "floor_tilt"), 1.5, seed=23, kind="held_out_7"),
        case("cube", ("com_offset", "floor_offset"), 1.5, seed=23, kind="held_out_7"),
        case("cube", ("coriolis",), 1.0, seed=23, velocities=False, kind="held_out_7"),
        case("icosahedron", ("floor_centring",), 1.5, seed=23, kind="held_out_7"),
        case("truncated_octahedron", ("floor_viscosity",), 2.0, seed=23, kind="held_out_7"),
        case("dodecahedron", ("spin_damping",), 2.0, seed=23, kind="held_out_7"),
    ]
    # Written after held_out_7 had been seen (right names left unconfirmed by the wide interval of full rollouts: a
    # name is now confirmed on test by the short-horizon loss it was chosen on, full rollouts not getting worse),
    # run once: seed 29, five nulls, every library effect, two pairs, every outside effect, shapes rotated.
    eighth = [
        case("octahedron", seed=29, kind="held_out_8"),
        case("dodecahedron", seed=29, velocities=False, kind="held_out_8"),
        case("cube", seed=29, kind="held_out_8"),
        case("truncated_octahedron", seed=29, velocities=False, kind="held_out_8"),
        case("tetrahedron", seed=29, kind="held_out_8"),
        case("icosahedron", ("air_drag",), 1.5, seed=29, velocities=False, kind="held_out_8"),
        case("cube", ("wind",), 1.5, seed=29, kind="held_out_8"),
        case("dodecahedron", ("torsional_friction",), 2.0, seed=29, kind="held_out_8"),
        case("rhombicuboctahedron", ("rolling_friction",), 2.0, seed=29, velocities=False, kind="held_out_8"),
        case("octahedron", ("anisotropic_friction",), 1.5, seed=29, kind="held_out_8"),
        case("truncated_octahedron", ("com_offset",), 1.5, seed=29, velocities=False, kind="held_out_8"),
        case("icosahedron", ("inertia_mismatch",), 2.0, seed=29, kind="held_out_8"),
        case("tetrahedron", ("floor_offset",), 1.5, seed=29, kind="held_out_8"),
        case("cube", ("floor_tilt",), 1.0, seed=29, velocities=False, kind="held_out_8"),
        case("dodecahedron", ("gravity_scale",), 2.0, seed=29, kind="held_out_8"),
        case("icosahedron", ("air_drag", "com_offset"), 1.5, seed=29, kind="held_out_8"),
        case("cube", ("floor_tilt", "inertia_mismatch"), 1.5, seed=29, kind="held_out_8"),
        case("octahedron", ("coriolis",), 1.0, seed=29, kind="held_out_8"),
        case("cube", ("floor_centring",), 1.5, seed=29, velocities=False, kind="held_out_8"),
        case("dodecahedron", ("floor_viscosity",), 2.0, seed=29, kind="held_out_8"),
        case("rhombicuboctahedron", ("spin_damping",), 2.0, seed=29, kind="held_out_8"),
    ]
    # Written after held_out_8 had been seen (the screen dropped a hidden torsional friction: quick fitted 9 of 10
    # effects; pairs lost their second effect to the base-loss margin; right names left unconfirmed by one horizon's
    # interval: every effect is now fitted, a later round closes 10% of its round's model's loss, and a name is
    # confirmed at either horizon), run once: seed 31, five nulls, every library effect, two pairs, every outside
    # effect.
    ninth = [
        case("icosahedron", seed=31, kind="held_out_9"),
        case("cube", seed=31, velocities=False, kind="held_out_9"),
        case("rhombicuboctahedron", seed=31, kind="held_out_9"),
        case("octahedron", seed=31, velocities=False, kind="held_out_9"),
        case("dodecahedron", seed=31, kind="held_out_9"),
        case("cube", ("air_drag",), 2.0, seed=31, kind="held_out_9"),
        case("tetrahedron", ("wind",), 1.5, seed=31, velocities=False, kind="held_out_9"),
        case("icosahedron", ("torsional_friction",), 2.0, seed=31, kind="held_out_9"),
        case("cube", ("rolling_friction",), 1.5, seed=31, kind="held_out_9"),
        case("truncated_octahedron", ("anisotropic_friction",), 2.0, seed=31, kind="held_out_9"),
        case("cube", ("com_offset",), 1.0, seed=31, velocities=False, kind="held_out_9"),
        case("octahedron", ("inertia_mismatch",), 2.0, seed=31, velocities=False, kind="held_out_9"),
        case("dodecahedron", ("floor_offset",), 1.0, seed=31, kind="held_out_9"),
        case("truncated_octahedron", ("floor_tilt",), 1.5, seed=31, velocities=False, kind="held_out_9"),
        case("cube", ("gravity_scale",), 1.5, seed=31, kind="held_out_9"),
        case("octahedron", ("wind", "com_offset"), 1.5, seed=31, kind="held_out_9"),
        case("tetrahedron", ("floor_tilt", "rolling_friction"), 1.5, seed=31, kind="held_out_9"),
        case("icosahedron", ("coriolis",), 1.0, seed=31, velocities=False, kind="held_out_9"),
        case("dodecahedron", ("floor_centring",), 1.5, seed=31, kind="held_out_9"),
        case("cube", ("floor_viscosity",), 2.0, seed=31, kind="held_out_9"),
        case("truncated_octahedron", ("spin_damping",), 3.0, seed=31, kind="held_out_9"),
    ]
    # Written after held_out_9 had been seen (a pair's true wind closed 9.6% of its round's loss, under the later
    # margin: a later effect may now close the first-round margin where it gains in free flight), run once: seed 37,
    # five nulls, every library effect, two pairs, every outside effect.
    tenth = [
        case("truncated_octahedron", seed=37, kind="held_out_10"),
        case("tetrahedron", seed=37, velocities=False, kind="held_out_10"),
        case("cube", seed=37, kind="held_out_10"),
        case("dodecahedron", seed=37, velocities=False, kind="held_out_10"),
        case("rhombicuboctahedron", seed=37, kind="held_out_10"),
        case("dodecahedron", ("air_drag",), 1.5, seed=37, kind="held_out_10"),
        case("cube", ("wind",), 1.0, seed=37, velocities=False, kind="held_out_10"),
        case("tetrahedron", ("torsional_friction",), 2.0, seed=37, kind="held_out_10"),
        case("truncated_octahedron", ("rolling_friction",), 1.5, seed=37, velocities=False, kind="held_out_10"),
        case("cube", ("anisotropic_friction",), 2.0, seed=37, kind="held_out_10"),
        case("tetrahedron", ("com_offset",), 1.5, seed=37, kind="held_out_10"),
        case("rhombicuboctahedron", ("inertia_mismatch",), 2.0, seed=37, velocities=False, kind="held_out_10"),
        case("truncated_octahedron", ("floor_offset",), 1.0, seed=37, kind="held_out_10"),
        case("cube", ("floor_tilt",), 1.5, seed=37, kind="held_out_10"),
        case("dodecahedron", ("gravity_scale",), 1.5, seed=37, velocities=False, kind="held_out_10"),
        case("tetrahedron", ("air_drag", "floor_offset"), 1.5, seed=37, kind="held_out_10"),
        case("dodecahedron", ("wind", "com_offset"), 1.5, seed=37, kind="held_out_10"),
        case("truncated_octahedron", ("coriolis",), 1.0, seed=37, kind="held_out_10"),
        case("tetrahedron", ("floor_centring",), 1.5, seed=37, velocities=False, kind="held_out_10"),
        case("rhombicuboctahedron", ("floor_viscosity",), 2.0, seed=37, kind="held_out_10"),
        case("cube", ("spin_damping",), 3.0, seed=37, kind="held_out_10"),
    ]
    # Written after held_out_10 had been seen (a tetrahedron's drag beside a floor offset went unjudged in free flight:
    # 15 of 165 val tosses fly clear for a 16-frame segment; the free-flight evidence now uses half-length segments),
    # run once: seed 41, five nulls, every library effect, two pairs, every outside effect.
    eleventh = [
        case("octahedron", seed=41, kind="held_out_11"),
        case("icosahedron", seed=41, velocities=False, kind="held_out_11"),
        case("tetrahedron", seed=41, kind="held_out_11"),
        case("cube", seed=41, velocities=False, kind="held_out_11"),
        case("truncated_octahedron", seed=41, kind="held_out_11"),
        case("tetrahedron", ("air_drag",), 1.5, seed=41, velocities=False, kind="held_out_11"),
        case("icosahedron", ("wind",), 1.5, seed=41, kind="held_out_11"),
        case("octahedron", ("torsional_friction",), 2.0, seed=41, kind="held_out_11"),
        case("icosahedron", ("rolling_friction",), 2.0, seed=41, kind="held_out_11"),
        case("octahedron", ("anisotropic_friction",), 2.0, seed=41, velocities=False, kind="held_out_11"),
        case("cube", ("com_offset",), 1.5, seed=41, kind="held_out_11"),
        case("truncated_octahedron", ("inertia_mismatch",), 2.0, seed=41, kind="held_out_11"),
        case("icosahedron", ("floor_offset",), 1.0, seed=41, velocities=False, kind="held_out_11"),
        case("octahedron", ("floor_tilt",), 1.5, seed=41, kind="held_out_11"),
        case("cube", ("gravity_scale",), 2.0, seed=41, kind="held_out_11"),
        case("octahedron", ("air_drag", "floor_tilt"), 1.5, seed=41, kind="held_out_11"),
        case("tetrahedron", ("com_offset", "floor_offset"), 1.5, seed=41, kind="held_out_11"),
        case("icosahedron", ("coriolis",), 1.0, seed=41, kind="held_out_11"),
        case("cube", ("floor_centring",), 1.5, seed=41, kind="held_out_11"),
        case("octahedron", ("floor_viscosity",), 2.0, seed=41, velocities=False, kind="held_out_11"),
        case("tetrahedron", ("spin_damping",), 3.0, seed=41, kind="held_out_11"),
    ]
    # Written after held_out_11 had been seen (an octahedron's air drag beside a floor tilt was lost: 2.6% of its
    # round's loss; free flight now measures drag model-free, and a measured drag is practically meaningful), run
    # once: seed 43, a null for every shape, every library effect, two pairs, every outside effect.
    twelfth = [
        case("cube", seed=43, kind="held_out_12"),
        case("dodecahedron", seed=43, velocities=False, kind="held_out_12"),
        case("rhombicuboctahedron", seed=43, kind="held_out_12"),
        case("tetrahedron", seed=43, velocities=False, kind="held_out_12"),
        case("icosahedron", seed=43, kind="held_out_12"),
        case("truncated_octahedron", seed=43, velocities=False, kind="held_out_12"),
        case("octahedron", seed=43, kind="held_out_12"),
        case("cube", ("air_drag",), 1.0, seed=43, velocities=False, kind="held_out_12"),
        case("truncated_octahedron", ("wind",), 1.5, seed=43, kind="held_out_12"),
        case("cube", ("torsional_friction",), 2.0, seed=43, kind="held_out_12"),
        case("dodecahedron", ("rolling_friction",), 1.5, seed=43, velocities=False, kind="held_out_12"),
        case("icosahedron", ("anisotropic_friction",), 2.0, seed=43, kind="held_out_12"),
        case("octahedron", ("com_offset",), 1.5, seed=43, kind="held_out_12"),
        case("cube", ("inertia_mismatch",), 2.0, seed=43, velocities=False, kind="held_out_12"),
        case("rhombicuboctahedron", ("floor_offset",), 1.5, seed=43, kind="held_out_12"),
        case("tetrahedron", ("floor_tilt",), 1.0, seed=43, kind="held_out_12"),
        case("truncated_octahedron", ("gravity_scale",), 2.0, seed=43, velocities=False, kind="held_out_12"),
        case("cube", ("air_drag", "inertia_mismatch"), 1.5, seed=43, kind="held_out_12"),
        case("dodecahedron", ("wind", "floor_offset"), 1.5, seed=43, kind="held_out_12"),
        case("octahedron", ("coriolis",), 1.0, seed=43, velocities=False, kind="held_out_12"),
        case("truncated_octahedron", ("floor_centring",), 1.5, seed=43, kind="held_out_12"),
        case("icosahedron", ("floor_viscosity",), 2.0, seed=43, kind="held_out_12"),
        case("octahedron", ("spin_damping",), 3.0, seed=43, kind="held_out_12"),
    ]
    # Written after held_out_12 had been seen (no wrong name, no false alarm; what free flight rules out, a drag or an
    # apparent gravity, may now not pass), run once: seed 47, a null for every shape, every library effect, two
    # pairs, every outside effect.
    thirteenth = [
        case("octahedron", seed=47, velocities=False, kind="held_out_13"),
        case("cube", seed=47, kind="held_out_13"),
        case("tetrahedron", seed=47, kind="held_out_13"),
        case("truncated_octahedron", seed=47, kind="held_out_13"),
        case("dodecahedron", seed=47, kind="held_out_13"),
        case("icosahedron", seed=47, velocities=False, kind="held_out_13"),
        case("rhombicuboctahedron", seed=47, velocities=False, kind="held_out_13"),
        case("octahedron", ("air_drag",), 2.0, seed=47, kind="held_out_13"),
        case("dodecahedron", ("wind",), 1.0, seed=47, velocities=False, kind="held_out_13"),
        case("truncated_octahedron", ("torsional_friction",), 2.0, seed=47, kind="held_out_13"),
        case("cube", ("rolling_friction",), 2.0, seed=47, kind="held_out_13"),
        case("tetrahedron", ("anisotropic_friction",), 2.0, seed=47, velocities=False, kind="held_out_13"),
        case("icosahedron", ("com_offset",), 1.5, seed=47, kind="held_out_13"),
        case("dodecahedron", ("inertia_mismatch",), 2.0, seed=47, kind="held_out_13"),
        case("cube", ("floor_offset",), 1.0, seed=47, velocities=False, kind="held_out_13"),
        case("rhombicuboctahedron", ("floor_tilt",), 1.5, seed=47, kind="held_out_13"),
        case("icosahedron", ("gravity_scale",), 1.5, seed=47, kind="held_out_13"),
        case("truncated_octahedron", ("air_drag", "com_offset"), 1.5, seed=47, kind="held_out_13"),
        case("cube", ("wind", "floor_tilt"), 1.5, seed=47, velocities=False, kind="held_out_13"),
        case("tetrahedron", ("coriolis",), 1.0, seed=47, kind="held_out_13"),
        case("octahedron", ("floor_centring",), 1.5, seed=47, kind="held_out_13"),
        case("cube", ("floor_viscosity",), 2.0, seed=47, kind="held_out_13"),
        case("dodecahedron", ("spin_damping",), 3.0, seed=47, kind="held_out_13"),
    ]
    # Written after held_out_13 had been seen (a rival that misses significance may tie with the best; a tie of two
    # is confounded; before it ran, the open world left the contact normal to the contact model, at one 5% margin),
    # run once: seed 53, a null for every shape, every library effect, two pairs, every outside effect.
    fourteenth = [
        case("rhombicuboctahedron", seed=53, kind="held_out_14"),
        case("icosahedron", seed=53, kind="held_out_14"),
        case("cube", seed=53, velocities=False, kind="held_out_14"),
        case("dodecahedron", seed=53, kind="held_out_14"),
        case("octahedron", seed=53, kind="held_out_14"),
        case("tetrahedron", seed=53, velocities=False, kind="held_out_14"),
        case("truncated_octahedron", seed=53, kind="held_out_14"),
        case("icosahedron", ("air_drag",), 1.5, seed=53, kind="held_out_14"),
        case("cube", ("wind",), 1.5, seed=53, kind="held_out_14"),
        case("octahedron", ("torsional_friction",), 2.0, seed=53, velocities=False, kind="held_out_14"),
        case("tetrahedron", ("rolling_friction",), 2.0, seed=53, kind="held_out_14"),
        case("cube", ("anisotropic_friction",), 1.5, seed=53, kind="held_out_14"),
        case("dodecahedron", ("com_offset",), 1.5, seed=53, velocities=False, kind="held_out_14"),
        case("octahedron", ("inertia_mismatch",), 2.0, seed=53, kind="held_out_14"),
        case("truncated_octahedron", ("floor_offset",), 1.0, seed=53, kind="held_out_14"),
        case("cube", ("floor_tilt",), 1.0, seed=53, velocities=False, kind="held_out_14"),
        case("rhombicuboctahedron", ("gravity_scale",), 1.5, seed=53, kind="held_out_14"),
        case("icosahedron", ("wind", "com_offset"), 1.5, seed=53, kind="held_out_14"),
        case("dodecahedron", ("air_drag", "floor_tilt"), 1.5, seed=53, velocities=False, kind="held_out_14"),
        case("cube", ("coriolis",), 1.0, seed=53, kind="held_out_14"),
        case("tetrahedron", ("floor_centring",), 1.5, seed=53, kind="held_out_14"),
        case("octahedron", ("floor_viscosity",), 2.0, seed=53, kind="held_out_14"),
        case("truncated_octahedron", ("spin_damping",), 3.0, seed=53, velocities=False, kind="held_out_14"),
    ]
    # Written after held_out_14 had been seen (an effect free flight measures may show its significance there), run
    # once: seed 59, a null for every shape, every library effect, two pairs, every outside effect.
    fifteenth = [
        case("cube", seed=59, kind="held_out_15"),
        case("dodecahedron", seed=59, velocities=False, kind="held_out_15"),
        case("octahedron", seed=59, kind="held_out_15"),
        case("tetrahedron", seed=59, kind="held_out_15"),
        case("icosahedron", seed=59, velocities=False, kind="held_out_15"),
        case("rhombicuboctahedron", seed=59, kind="held_out_15"),
        case("truncated_octahedron", seed=59, velocities=False, kind="held_out_15"),
        case("tetrahedron", ("air_drag",), 2.0, seed=59, velocities=False, kind="held_out_15"),
        case("octahedron", ("wind",), 1.0, seed=59, kind="held_out_15"),
        case("dodecahedron", ("torsional_friction",), 2.0, seed=59, kind="held_out_15"),
        case("icosahedron", ("rolling_friction",), 2.0, seed=59, velocities=False, kind="held_out_15"),
        case("octahedron", ("anisotropic_friction",), 2.0, seed=59, kind="held_out_15"),
        case("tetrahedron", ("com_offset",), 1.5, seed=59, kind="held_out_15"),
        case("truncated_octahedron", ("inertia_mismatch",), 2.0, seed=59, velocities=False, kind="held_out_15"),
        case("cube", ("floor_offset",), 1.5, seed=59, kind="held_out_15"),
        case("icosahedron", ("floor_tilt",), 1.5, seed=59, kind="held_out_15"),
        case("dodecahedron", ("gravity_scale",), 2.0, seed=59, kind="held_out_15"),
        case("rhombicuboctahedron", ("air_drag", "com_offset"), 1.5, seed=59, kind="held_out_15"),
        case("octahedron", ("wind", "floor_offset"), 1.5, seed=59, velocities=False, kind="held_out_15"),
        case("dodecahedron", ("coriolis",), 1.0, seed=59, velocities=False, kind="held_out_15"),
        case("icosahedron", ("floor_centring",), 1.5, seed=59, kind="held_out_15"),
        case("truncated_octahedron", ("floor_viscosity",), 2.0, seed=59, kind="held_out_15"),
        case("cube", ("spin_damping",), 3.0, seed=59, kind="held_out_15"),
    ]
    return [
        *tuning,
        *held,
        *second,
        *third,
        *fourth,
        *fifth,
        *sixth,
        *seventh,
        *eighth,
        *ninth,
        *tenth,
        *eleventh,
        *twelfth,
        *thirteenth,
        *fourteenth,
        *fifteenth,
    ]


def case_name(case: dict) -> str:
    effects = "+".join(case["effects"])
    return (
        f"{case['shape']}_seed{case['seed']}_"
        + (f"{effects}_x{case['strength']:g}" if effects else "null")
        + ("" if case["velocities"] else "_novel")
    )


def generated_name(case: dict) -> str:
    """Velocities are stripped from the blind copy only: a case with and without them shares its generation."""
    return case_name({**case, "velocities": True})


def blind_copy(case: dict, index: int, data_dir: Path) -> tuple[Path, list[dict]]:
    """Generate the case (kept if there), then a copy without meta.generator under a neutral name."""
    source = data_dir / "generated" / generated_name(case)
    if not (source / "meta.json").exists():
        generate_dataset(
            SHAPES[case["shape"]],
            source,
            variant=generated_name(case),
            seed=case["seed"],
            effects=tuple(case["effects"]),
            effect_strength=case["strength"] or 1.0,
            progress=False,
        )
    full = read_recordings(source)
    hidden = full.meta["generator"]["effects"]
    blind = full.for_models(list(full.splits))
    if not case["velocities"]:
        blind = dataclasses.replace(
            blind, splits={name: dataclasses.replace(split, velocities=None) for name, split in blind.splits.items()}
        )
    blind.meta["name"] = f"blind-{index:02d}"
    target = data_dir / "blind" / f"blind-{index:02d}"
    write_recordings(target, blind)
    return target, hidden


def judge(case: dict, document: dict) -> dict:
    """Right, wrong name, false alarm or miss, against the hidden truth."""
    named = [e["name"] for e in document["effects"]]
    verdict = document["verdict"]
    truth = case["effects"]
    located = (document.get("open_world") or {}).get("located", {}).get("phase")
    if not truth:
        outcome = "right" if verdict == "none" else "false alarm"
    elif truth[0] in OUTSIDE_LIBRARY:
        if named:
            outcome = "wrong name"
        elif verdict == "unexplained":
            outcome = "right" if located in ACTS_IN[truth[0]] else "wrong place"
        else:
            outcome = "miss"
    elif any(name not in truth for name in named):
        outcome = "wrong name"
    elif sorted(named) == sorted(truth):
        outcome = "right" if document["heldout"]["confirmed"] else "unconfirmed"
    else:
        outcome = "miss"  # none, unexplained, or only some of two effects
    return {"named": named, "verdict": verdict, "located": located, "outcome": outcome}


def diagnose(path: Path, out_dir: Path, budget: str) -> dict:
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("diagnose", overrides=[f"recordings={path}", f"budget={budget}"])
    runs.diagnose(cfg, out_dir)
    return json.loads((out_dir / "diagnosis.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="*", default=None, help="run the cases with any of these effects (null: nulls)")
    parser.add_argument("--set", choices=SETS, default=None, help="run one set only")
    parser.add_argument("--budget", default="quick")
    parser.add_argument("--data", type=Path, default=ROOT / "data" / "proof")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "proof")
    args = parser.parse_args()
    started = time.perf_counter()
    rows, null_base = [], {}
    for index, listed in enumerate(cases()):
        wanted = set(args.only or ()) & (set(listed["effects"]) or {"null"})
        if (args.only is not None and not wanted) or (args.set and listed["set"] != args.set):
            continue
        path, hidden = blind_copy(listed, index, args.data)
        case_started = time.perf_counter()
        document = diagnose(path, args.out / f"blind-{index:02d}", args.budget)
        held = document["heldout"]
        base, augmented = held["base"]["pos_err"], held["augmented"]["pos_err"]
        if not listed["effects"]:
            null_base.setdefault((listed["shape"], listed["seed"]), base)
        reference = null_base.get((listed["shape"], listed["seed"]))
        excess = base - reference if reference is not None else float("nan")
        named = bool(document["effects"])
        open_world = document.get("open_world") or {}
        row = {
            **listed,
            "name": case_name(listed),
            "blind": path.name,
            **judge(listed, document),
            "hidden": {h["name"]: h["parameters"] for h in hidden},
            "fitted": {e["name"]: e["parameters"] for e in document["effects"]},
            "base_pos_err": base,
            "augmented_pos_err": augmented,
            "null_base_pos_err": reference,
            "excess_closed": (base - augmented) / excess if named and excess > 0 else None,
            "heldout_improvement": held["improvement"] if named else None,
            "heldout_ci95": held["ci95"] if named else None,
            "open_world_val": open_world.get("val_improvement"),
            "open_world_heldout": (open_world.get("heldout") or {}).get("improvement"),
            "seconds": round(time.perf_counter() - case_started, 1),
        }
        rows.append(row)
        print(
            f"{row['name']:48s} -> {row['verdict']} {row['named'] or ''} {row['located'] or ''} "
            f"{row['outcome'].upper()}  base {base:.4f} aug {augmented:.4f} closed {row['excess_closed']}  "
            f"open world {row['open_world_val']}  ({row['seconds']} s)",
            flush=True,
        )
    summary = summarise(rows, time.perf_counter() - started)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic.write_json(args.out / "proof.json", {"summary": summary, "cases": rows})
    atomic.write_text(args.out / "proof.md", summary["markdown"])
    print(summary["markdown"])


def _truth_label(row: dict) -> str:
    return "+".join(row["effects"]) or "none"


def _predicted_label(row: dict) -> str:
    if row["verdict"] in ("none", "unexplained", "confounded"):
        return row["verdict"]
    if row["verdict"] == "unconfirmed":
        return "unconfirmed"
    return "+".join(sorted(row["named"]))


def _rate(rows: list[dict]) -> str:
    return f"{sum(r['outcome'] == 'right' for r in rows)} of {len(rows)}" if rows else "n/a"


def summarise(rows: list[dict], seconds: float) -> dict:
    library_rows = [r for r in rows if r["effects"] and r["effects"][0] not in OUTSIDE_LIBRARY]
    outside_rows = [r for r in rows if r["effects"] and r["effects"][0] in OUTSIDE_LIBRARY]
    null_rows = [r for r in rows if not r["effects"]]
    truths = sorted({_truth_label(r) for r in rows})
    special = ["unconfirmed", "unexplained", "confounded", "none"]
    predicted = sorted({_predicted_label(r) for r in rows} - set(special)) + special
    matrix = {truth: {label: 0 for label in predicted} for truth in truths}
    for r in rows:
        matrix[_truth_label(r)][_predicted_label(r)] += 1
    closed = [r["excess_closed"] for r in library_rows if r["outcome"] == "right" and r["excess_closed"] is not None]
    wrong = [r["name"] for r in rows if r["outcome"] == "wrong name"]
    false_alarms = [r["name"] for r in null_rows if r["outcome"] != "right"]
    lines = [
        f"# Diagnosis proof ({len(rows)} blind datasets, {seconds / 60:.1f} min, "
        f"{max((r['seconds'] for r in rows), default=0):.0f} s for the slowest)",
        "",
        f"- library effects named right: {_rate(library_rows)} (goal >= 95%); "
        + ", ".join(
            f"{name} {_rate([r for r in library_rows if r['set'] == name])}"
            for name in SETS
            if any(r["set"] == name for r in library_rows)
        ),
        f"- wrong names: {len(wrong)} (goal 0){': ' + ', '.join(wrong) if wrong else ''}",
        f"- false alarms: {len(false_alarms)} of {len(null_rows)} nulls (goal 0)"
        f"{': ' + ', '.join(false_alarms) if false_alarms else ''}",
        f"- outside the library, `unexplained` in the right phase: {_rate(outside_rows)} (goal >= 2 of 3)",
        f"- excess held-out error closed where named right: median {np.median(closed):.0%}, mean "
        f"{np.mean(closed):.0%} over {len(closed)} (goal median >= 50%)"
        if closed
        else "- excess closed: n/a",
        "",
        "## Confusion matrix (rows: hidden, columns: verdict)",
        "",
        "| hidden \\ verdict | " + " | ".join(predicted) + " |",
        "|---|" + "---|" * len(predicted),
        *[f"| {truth} | " + " | ".join(str(matrix[truth][p]) for p in predicted) + " |" for truth in truths],
        "",
        "## Cases",
        "",
        "| set | dataset | verdict | outcome | base | augmented | base without effect | excess closed | open world "
        "val / test | hidden | fitted | s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        closed_text = "–" if r["excess_closed"] is None else f"{r['excess_closed']:.0%}"
        verdict = ", ".join(r["named"]) or r["verdict"]
        if r["verdict"] == "unexplained":
            verdict += f" ({r['located']})"
        open_world = "–" if r["open_world_val"] is None else f"{r['open_world_val']:.1%}"
        if r["open_world_heldout"] is not None:
            open_world += f" / {r['open_world_heldout']:.1%}"
        lines.append(
            f"| {r['set']} | {r['name']} | {verdict} | {r['outcome']} | {r['base_pos_err']:.4f} | "
            f"{r['augmented_pos_err']:.4f} | "
            f"{'–' if r['null_base_pos_err'] is None else format(r['null_base_pos_err'], '.4f')} | {closed_text} | "
            f"{open_world} | {_short(r['hidden'])} | {_short(r['fitted'])} | {r['seconds']} |"
        )
    return {
        "library_named_right": _rate(library_rows),
        "outside_unexplained_right": _rate(outside_rows),
        "wrong_names": wrong,
        "false_alarms": false_alarms,
        "nulls": len(null_rows),
        "excess_closed_median": float(np.median(closed)) if closed else None,
        "confusion": matrix,
        "seconds": seconds,
        "markdown": "\n".join(lines) + "\n",
    }


def _short(values: dict) -> str:
    return "; ".join(
        f"{name}: " + ", ".join(f"{k}={v:.3g}" for k, v in parameters.items()) for name, parameters in values.items()
    )


if __name__ == "__main__":
    main()
