"""diagnosis.contact_signatures: friction, spin, rolling and bounce read off recorded contact with no simulator, on
small PyBullet datasets whose concealed physics is known."""

from __future__ import annotations

import json

import numpy as np
import pytest

from contactbench.diagnosis import contact_signatures as signatures
from contactbench.diagnosis.free_flight import INCONCLUSIVE, MEASURED, RULED_OUT
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.recordings import read_recordings

CUBE = SceneSpec("frictioncubes", friction=0.5, restitution=0.0)
ICOSAHEDRON = SceneSpec("polyhedra", friction=0.5, restitution=0.125, faces=20)
SIZES = {"train": 30, "val": 40, "test": 40}
VARIANTS = {
    "cube": (CUBE, (), 1.0),
    "anisotropic": (CUBE, ("anisotropic_friction",), 2.0),
    "torsional": (CUBE, ("torsional_friction",), 1.0),
    "icosahedron": (ICOSAHEDRON, (), 1.0),
    "rolling": (ICOSAHEDRON, ("rolling_friction",), 1.0),
}


@pytest.fixture(scope="module")
def found(tmp_path_factory) -> dict[str, dict]:
    """Each variant's signatures, measured as diagnose.py would: only what a model may see."""
    root = tmp_path_factory.mktemp("signatures")
    out = {}
    for name, (spec, effects, strength) in VARIANTS.items():
        path = generate_dataset(
            spec, root / name, split_sizes=SIZES, workers=1, progress=False, effects=effects, effect_strength=strength
        )
        dataset = read_recordings(path)
        out[name] = signatures.measure(dataset.for_models(list(dataset.splits)), np.random.default_rng(0), 200)
    return out


def test_a_concealed_anisotropic_friction_is_measured_along_x_and_a_null_cube_rules_it_out(found):
    anisotropic = found["anisotropic"]
    assert anisotropic["evidence"]["anisotropic_friction"] == MEASURED
    assert anisotropic["signatures"]["anisotropy"]["confirmed"]
    val = anisotropic["splits"]["val"]["anisotropy"]
    # the floor's friction is 2x larger along world x than along y: mu(theta) peaks at 0 degrees
    assert val["value"] > 0.15 and val["ci"][0] > signatures.ANISOTROPY_MARGIN
    assert abs(val["axis_deg"]) < 15
    assert "evidence for library effect anisotropic_friction" in anisotropic["signatures"]["anisotropy"]["sentence"]
    null = found["cube"]
    assert null["evidence"]["anisotropic_friction"] == RULED_OUT
    for part in null["splits"].values():
        assert part["anisotropy"]["mu0"] == pytest.approx(0.5, abs=0.02)  # the recorded material's friction
        assert part["anisotropy"]["ci"][1] < signatures.ANISOTROPY_MARGIN
    # nothing else in the null cube's sliding: no speed dependence
    assert null["signatures"]["speed"]["evidence"] == RULED_OUT


def test_torsional_friction_holds_a_sliding_body_s_spin_and_a_null_cube_keeps_spinning(found):
    torsional, null = found["torsional"], found["cube"]
    assert torsional["evidence"]["torsional_friction"] == MEASURED
    assert torsional["splits"]["val"]["spin_held"]["ci"][0] > signatures.HELD_MARGIN
    assert null["evidence"]["torsional_friction"] == RULED_OUT
    assert null["splits"]["val"]["spin_held"]["ci"][1] < 0.25
    # pivoting on a vertex, Coulomb friction has no spin torque: the null's spin torque per load is zero
    assert abs(null["splits"]["val"]["spin"]["value"]) < 1e-3


def test_rolling_friction_is_measured_in_metres_and_a_null_icosahedron_rules_it_out(found):
    rolling = found["rolling"]
    assert rolling["evidence"]["rolling_friction"] == MEASURED
    for part in rolling["splits"].values():
        assert part["rolling"]["value"] == pytest.approx(0.01, abs=0.0015)  # PyBullet's rollingFriction, 0.01 m
    null = found["icosahedron"]
    assert null["evidence"]["rolling_friction"] == RULED_OUT
    assert null["splits"]["val"]["rolling"]["ci"][1] < signatures.ROLLING_MARGIN
    # an icosahedron seldom slides flat on a face: friction's direction cannot be read off it
    assert null["evidence"]["anisotropic_friction"] == INCONCLUSIVE


def test_every_signature_says_what_it_speaks_to_and_bounces_are_read(found):
    for result in found.values():
        assert set(result["signatures"]) == set(signatures.SPEAKS_TO)
        for name, signature in result["signatures"].items():
            assert signature["speaks_to"] == signatures.SPEAKS_TO[name] and signature["sentence"]
    # a cube tossed with restitution 0 still rebounds a little at its landing vertex (it rotates), an icosahedron
    # with restitution 0.125 more
    cube, icosahedron = found["cube"]["splits"]["val"]["bounce"], found["icosahedron"]["splits"]["val"]["bounce"]
    assert 0 < cube["value"] < icosahedron["value"] < 0.5


def test_the_same_seed_gives_the_same_numbers(tmp_path):
    path = generate_dataset(CUBE, tmp_path / "cube", split_sizes=SIZES, workers=1, progress=False)
    dataset = read_recordings(path).for_models(["train", "val", "test"])
    first = signatures.measure(dataset, np.random.default_rng(3), 100)
    again = signatures.measure(dataset, np.random.default_rng(3), 100)
    other = signatures.measure(dataset, np.random.default_rng(4), 100)
    assert json.dumps(first, sort_keys=True) == json.dumps(again, sort_keys=True)
    # another seed resamples other tosses: the same point estimates, other intervals
    val, other_val = first["splits"]["val"]["anisotropy"], other["splits"]["val"]["anisotropy"]
    assert val["mu0"] == other_val["mu0"] and val["ci"] != other_val["ci"]


@pytest.mark.parametrize(
    ("val_ci", "test", "two_sided", "expected"),
    [
        ([0.08, 0.12], {"value": 0.09, "ci": [0.05, 0.13]}, True, (MEASURED, True)),
        ([0.08, 0.12], {"value": 0.03, "ci": [0.01, 0.06]}, True, (INCONCLUSIVE, False)),  # test does not agree
        ([0.08, 0.12], {}, True, (MEASURED, False)),  # test too small to say
        ([-0.12, -0.08], {"value": -0.09, "ci": [-0.12, -0.06]}, True, (MEASURED, True)),
        ([-0.12, -0.08], {"value": -0.09, "ci": [-0.12, -0.06]}, False, (INCONCLUSIVE, False)),  # a size: noise
        ([-0.01, 0.02], {}, True, (RULED_OUT, False)),
        ([-0.3, 0.02], {}, False, (INCONCLUSIVE, False)),  # a debiased size swamped by noise is not ruled out
        ([0.02, 0.07], {}, True, (INCONCLUSIVE, False)),
    ],
)
def test_evidence_against_a_margin_on_val_confirmed_on_test(val_ci, test, two_sided, expected):
    val = {"value": float(np.mean(val_ci)), "ci": val_ci}
    assert signatures.evidence(val, test, 0.05, two_sided) == expected
