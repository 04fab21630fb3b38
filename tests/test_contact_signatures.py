"""diagnosis.contact_signatures: friction, spin, rolling and bounce read off recorded contact with no simulator, on
small PyBullet datasets whose concealed physics is known."""

from __future__ import annotations

import dataclasses
import json

import mujoco
import numpy as np
import pytest

from contactbench import rotations
from contactbench.config import REPO_ROOT
from contactbench.diagnosis import contact_kinematics, contact_rows
from contactbench.diagnosis import contact_signatures as signatures
from contactbench.diagnosis.free_flight import INCONCLUSIVE, MEASURED, RULED_OUT
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.kinematics import hinge_child
from contactbench.recordings import read_recordings
from contactbench.scene import Recordings, Split
from contactbench.sim.engines import engine
from contactbench.sim.mujoco_scene import ContactParameters

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
            assert "hinged" not in signature  # free bodies only: nothing read through a tree
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


# ---------------------------------------------------------------- bodies on joints


def _hinged_slides(n: int = 8, frames: int = 60) -> Recordings:
    """The real elbow's two bars, simulated in MuJoCo: the parent bar lies on a 5 cm face with the hinge axis upright,
    sliding at 1.5 m/s, the child bar above it whirling about the hinge at 6-10 rad/s, clear of the floor. Friction
    0.3 on an elliptic cone (MuJoCo's default pyramid makes the friction depend on the slip's direction)."""
    elbow = read_recordings(REPO_ROOT / "assets" / "contactnets_elbow")
    rng = np.random.default_rng(0)
    upright = rotations.from_axis_angle(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # the bar's y axis, the hinge's, up
    half_height = elbow.body_mesh(0).vertices[:, 1].max()
    yaw = [rotations.from_axis_angle(np.array([0.0, 0.0, 1.0]), a) for a in rng.uniform(-np.pi, np.pi, n)]
    parent = np.zeros((n, 7))
    parent[:, 2] = half_height + 1e-4
    parent[:, 3:] = [rotations.multiply(q, upright) for q in yaw]
    heading = rng.uniform(-np.pi, np.pi, n)
    parent_velocity = np.zeros((n, 6))
    parent_velocity[:, :2] = 1.5 * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    rate = rng.choice([-1.0, 1.0], n) * rng.uniform(6.0, 10.0, n)
    child, child_velocity = hinge_child(parent, parent_velocity, elbow.joints[0], rng.uniform(-np.pi, np.pi, n), rate)
    poses0, velocities0 = np.stack([parent, child], axis=1), np.stack([parent_velocity, child_velocity], axis=1)
    rollouts = engine("mujoco").rollouts(elbow, substeps=10)
    params = ContactParameters(object_friction=(0.3, 0.3), floor_friction=0.3, floor_stiffness=None, floor_damping=None)
    rollouts.model(params).opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    result = rollouts.simulate(params, poses0, velocities0, frames)
    assert not result.unstable.any()
    poses = np.concatenate([poses0[:, None], result.poses[0]], axis=1)
    split = Split(poses=poses, lengths=np.full(n, frames + 1))  # velocities: backward differences of the poses
    return dataclasses.replace(elbow, splits={"train": split})


def test_a_hinged_bar_sliding_under_a_whirling_one_reads_the_friction_through_the_pair_s_momentum():
    slides = _hinged_slides()
    split = slides.split("train")
    rows = contact_rows.split_rows(slides, split)["sliding"]
    assert len(np.unique(rows.toss)) == split.n_trajectories and len(rows.toss) > 100
    ratios = rows.response / rows.design[:, 0]
    assert np.percentile(ratios, [5, 95]) == pytest.approx([0.3, 0.3], abs=0.03)
    mu = float(rows.design[:, 0] @ rows.response / (rows.design[:, 0] @ rows.design[:, 0]))
    assert mu == pytest.approx(0.3, abs=0.01)
    # Read alone, the sliding bar's own motion carries the hinge's pull: its push over its load strays far off mu.
    pair = contact_kinematics.tree_kinematics(slides, split, (0, 1))[0]
    alone = contact_kinematics.body_kinematics(slides, split, 0)
    sliding = pair["in_contact"].copy()
    sliding[:, 0] = False
    sliding[:, 1:] &= pair["in_contact"][:, :-1]
    quartiles = {}
    for name, reading in (("pair", pair), ("alone", alone)):
        push = reading["push"][sliding]
        quartiles[name] = np.percentile(np.linalg.norm(push[:, :2], axis=-1) / push[:, 2], [25, 75])
    assert quartiles["pair"] == pytest.approx([0.3, 0.3], abs=0.02)
    assert np.ptp(quartiles["alone"]) > 0.15


def test_a_flying_hinged_pair_has_no_floor_force_or_torque_though_each_link_feels_the_hinge(tmp_path):
    spec = SceneSpec("articulated", friction=0.3, restitution=0.125, shape="elbow", bodies=2)
    elbow = read_recordings(generate_dataset(spec, tmp_path, split_sizes={"train": 20}, workers=1, progress=False))
    split = elbow.split("train")
    pair = contact_kinematics.tree_kinematics(elbow, split, (0, 1))
    flying = pair[0]["flying"].copy()
    flying[:, 0] = False
    flying[:, 1:] &= pair[0]["flying"][:, :-1]
    assert flying.sum() > 200 and (pair[0]["flying"] == pair[1]["flying"]).all()
    tree_torque = np.median(np.linalg.norm(pair[0]["torque_per_mass"][flying], axis=-1))
    assert np.median(np.linalg.norm(pair[0]["push"][flying], axis=-1)) < 0.05  # m/s^2 per unit mass: none
    for link in (0, 1):
        alone = contact_kinematics.body_kinematics(elbow, split, link)
        assert np.median(np.linalg.norm(alone["push"][flying], axis=-1)) > 0.1
        assert tree_torque < 0.2 * np.median(np.linalg.norm(alone["torque_per_mass"][flying], axis=-1))


def test_the_real_elbow_s_bars_are_read_in_contact_and_each_signature_says_how():
    elbow = read_recordings(REPO_ROOT / "assets" / "contactnets_elbow")
    found = signatures.measure(elbow.for_models(list(elbow.splits)), np.random.default_rng(0), 100)
    assert set(found["signatures"]) == set(signatures.SPEAKS_TO)
    for split in found["splits"].values():
        for name in ("anisotropy", "spin", "bounce"):
            assert split[name]["n_tosses"] >= signatures.MIN_TOSSES
    for name, signature in found["signatures"].items():
        assert signature["hinged"] == signatures.HINGED[name] or signature["hinged"].startswith(
            signatures.HINGED[name] + " Too few tosses"
        )
        assert signature["hinged"] in signature["sentence"]
    # too few of its frames roll over an edge with the other bar clear: said, with the counts
    assert "Too few tosses with such frames" in found["signatures"]["rolling"]["hinged"]
