"""The flexible-correction check before `none`: its integration is the open world's kinematics, its shuffles cut one
group and keep the rest, it learns a planted dependence and nothing in noise, turning the states tells a force fixed
in the world from one along the slip, and on generated tosses it passes a concealed floor bowl (on the place on the
floor, in contact) but not a null, deterministically."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from test_diagnose import CUBE

from contactbench.diagnosis import open_world, predictable, predictable_correction, predictable_states
from contactbench.diagnosis.bases import engine_bases
from contactbench.diagnosis.fitting import ResidualFit
from contactbench.diagnosis.library import Hypothesis
from contactbench.diagnosis.phases import FREE, PHASES, REST, ROLLING, SLIDING
from contactbench.diagnosis.segments import SegmentSimulator
from contactbench.diagnosis.state import Budget, Diagnosis
from contactbench.generation.generator import generate_dataset
from contactbench.recordings import read_recordings

pytestmark = pytest.mark.usefixtures("one_torch_thread")

DT = 0.01
LENGTH = 16
# Enough tosses for intervals a few percent wide; about 5 s per dataset (generation, base fit, check) on 2 cores.
SIZES = {"train": 30, "val": 40, "test": 30}
SMALL = Budget(fit_trajectories=30, val_trajectories=40, base_evaluations=16, batch=8, lsq_iterations=3, bootstrap=500)
CONTACT = {PHASES[p] for p in (SLIDING, ROLLING, REST)}


def test_the_correction_integrates_accelerations_as_the_open_world_does():
    rng = np.random.default_rng(0)
    features = rng.normal(size=(3, LENGTH, 1, len(open_world.FEATURES)))
    phases = np.full((3, LENGTH, 1), FREE)
    dictionary = open_world.integrate(features, phases, DT, np.array([2.0]))  # half width 1: no rescaling
    integration = open_world.integration_matrix(LENGTH, DT)
    accelerations = np.repeat(features[..., 3:4], 6, axis=-1)  # v_z as the acceleration of every output
    np.testing.assert_allclose(
        predictable_correction.integrate(integration, accelerations)[..., 0],
        dictionary.linear[..., FREE, 3],
        atol=1e-15,
    )
    # a constant acceleration a moves frame j by a dt^2 j (j + 1) / 2 (semi-implicit Euler on the frame grid)
    j = np.arange(1, LENGTH + 1)
    np.testing.assert_allclose(integration.sum(axis=1), DT**2 * j * (j + 1) / 2)


def random_states(rng: np.random.Generator, count: int = 40) -> predictable_states.States:
    shape = (count, LENGTH, 1)
    return predictable_states.States(
        velocity=rng.normal(size=(*shape, 3)),
        spin=rng.normal(size=(*shape, 3)),
        slip=rng.normal(size=(*shape, 2)),
        lowest_v_z=rng.normal(size=shape),
        height=rng.uniform(0.5, 2.0, size=shape),
        clearance=rng.uniform(0.0, 1.0, size=shape),
        up=rng.normal(size=(*shape, 3)),
        place=rng.uniform(-0.4, 0.4, size=(*shape, 2)),
        phase=rng.choice([FREE, SLIDING], size=shape),
    )


def test_shuffling_a_group_cuts_it_and_keeps_the_phase_and_everything_else():
    rng = np.random.default_rng(1)
    states = random_states(rng)
    heading = states.permuted("direction", rng)
    # the size of every velocity along the floor is kept, its heading is another state's of the same phase
    np.testing.assert_allclose(
        np.linalg.norm(heading.velocity[..., :2], axis=-1), np.linalg.norm(states.velocity[..., :2], axis=-1)
    )
    np.testing.assert_array_equal(heading.velocity[..., 2], states.velocity[..., 2])
    assert not np.allclose(heading.velocity[..., :2], states.velocity[..., :2])
    place = states.permuted("floor_position", rng)
    np.testing.assert_array_equal(place.phase, states.phase)
    for phase in (FREE, SLIDING):  # the same places, handed among the states of one phase
        where = states.phase == phase
        np.testing.assert_array_equal(np.sort(place.place[where], axis=0), np.sort(states.place[where], axis=0))
    np.testing.assert_array_equal(place.velocity, states.velocity)
    assert not np.array_equal(place.place, states.place)
    everything = states.permuted("constant", rng)
    np.testing.assert_array_equal(everything.phase, states.phase)
    assert not np.array_equal(everything.spin, states.spin) and not np.array_equal(everything.height, states.height)


class _Simulator:
    """What a check needs of a SegmentSimulator: the segments' trajectories and the per-trajectory loss."""

    trajectory_losses = SegmentSimulator.trajectory_losses

    def __init__(self, trajectory: np.ndarray):
        self.segments = SimpleNamespace(trajectory=trajectory, length=LENGTH)


def planted_inputs(rng: np.random.Generator, missing) -> predictable_states.Inputs:
    """Residuals of a simulator that misses the accelerations `missing(states)` [M, L, K, 6] (residual units per s^2),
    plus noise, on 30 tosses of 4 segments."""
    states = random_states(rng, count=120)
    noise = 2e-4 * rng.normal(size=(*states.phase.shape, 6))
    residuals = -predictable_correction.integrate(open_world.integration_matrix(LENGTH, DT), missing(states)) + noise
    fit = ResidualFit(_Simulator(np.repeat(np.arange(30), 4)), scale=1e-3)
    return predictable_states.Inputs(residuals, states, states.features(), np.ones(120, bool), fit, 30)


def sliding(states: predictable_states.States, x: np.ndarray, y: np.ndarray | float = 0.0) -> np.ndarray:
    """Accelerations (x, y) along the floor in the sliding states, nothing else."""
    out = np.zeros((*states.phase.shape, 6))
    out[..., 0], out[..., 1] = x, y
    return out * (states.phase == SLIDING)[..., None]


def learned(missing, seed: int = 2) -> tuple[predictable_correction.Correction, predictable_states.Inputs, dict]:
    """The correction fitted to planted train residuals, and judged on val residuals planted the same way."""
    rng = np.random.default_rng(seed)
    train, val = planted_inputs(rng, missing), planted_inputs(rng, missing)
    short = predictable_correction.Settings(max_steps=250)  # a planted force is learned to >90% by then (600: 95%)
    correction, _ = predictable_correction.train(train, DT, short)
    return correction, val, predictable.judged(correction, val, 500, 0.95, short)


def test_a_planted_dependence_on_the_place_is_learned_where_it_acts_and_noise_teaches_nothing():
    correction, val, judged = learned(lambda states: sliding(states, -40.0 * states.place[..., 0]))  # a floor bowl
    assert judged["ci95"][0] > 0.5  # most of the loss is the planted force, and the correction predicts it on val
    place = judged["statistics"]["floor_position"]
    assert place["ci95"][0] > 0.5 and place["gain"] > 0.8 * judged["gain"]
    assert abs(judged["statistics"]["spin"]["gain"]) < 0.05  # the spin carries nothing
    shares = predictable.phase_shares(correction, val)
    assert max(shares, key=shares.get) == PHASES[SLIDING]
    _, _, judged = learned(lambda states: sliding(states, 0.0))
    assert judged["ci95"][0] < 0.01


def test_turning_the_states_cuts_a_force_fixed_in_the_world_and_not_one_along_the_slip():
    rng = np.random.default_rng(3)
    states = random_states(rng)
    turned = states.turned(rng.uniform(0, 2 * np.pi, states.phase.shape))
    np.testing.assert_allclose(np.linalg.norm(turned.slip, axis=-1), np.linalg.norm(states.slip, axis=-1))
    np.testing.assert_array_equal(turned.velocity[..., 2], states.velocity[..., 2])
    np.testing.assert_array_equal(turned.place, states.place)
    _, _, wind = learned(lambda states: sliding(states, 5.0, 3.0))  # a push along a fixed direction of the floor
    assert wind["ci95"][0] > 0.5 and wind["statistics"]["heading"]["ci95"][0] > 0.5 * wind["gain"]
    _, _, friction = learned(lambda states: sliding(states, -8.0 * states.slip[..., 0], -8.0 * states.slip[..., 1]))
    assert friction["ci95"][0] > 0.5 and friction["statistics"]["heading"]["ci95"][1] < 0.1 * friction["gain"]


def fitted_steps(tmp_path_factory, effects: tuple[str, ...], strength: float = 1.0):
    path = generate_dataset(
        CUBE,
        tmp_path_factory.mktemp("predictable") / ("+".join(effects) or "null"),
        split_sizes=SIZES,
        workers=1,
        progress=False,
        effects=effects,
        effect_strength=strength,
    )
    steps = Diagnosis(read_recordings(path).for_models(["train", "val", "test"]), SMALL)
    return (steps, *steps.fit_base())


@pytest.fixture(scope="module")
def bowl(tmp_path_factory):
    return fitted_steps(tmp_path_factory, ("floor_centring",), 2.0)


@pytest.fixture(scope="module")
def null(tmp_path_factory):
    return fitted_steps(tmp_path_factory, ())


def test_a_concealed_floor_bowl_passes_in_contact_on_the_place_on_the_floor(bowl):
    record = predictable.check(*bowl)
    assert record["test"]["ci95"][0] > 0 and record["val"]["ci95"][0] > 0
    assert record["passes"] and "floor_position" in record["beyond_nulls"]
    assert record["depends_on"] == "floor_position" and record["phase"] in CONTACT
    assert "position on the floor" in record["sentence"]


def test_a_null_does_not_pass_and_the_check_is_deterministic_and_leaves_the_pipeline_draws_alone(null):
    steps, base, values = null
    drawn = steps.rng.bit_generator.state
    quick = predictable_correction.Settings(max_steps=60, permutations=1)
    record = predictable.check(steps, base, values, quick)
    assert steps.rng.bit_generator.state == drawn
    assert predictable.check(steps, base, values, quick) == record
    record = predictable.check(steps, base, values)
    assert not record["passes"] and record["beyond_nulls"] == []
    assert record["null_gain_bounds"] == predictable.NULL_GAIN_BOUNDS["mujoco"]  # the MuJoCo base's own bounds
    for name, bound in record["null_gain_bounds"].items():
        assert record["test"]["statistics"][name]["ci95"][0] <= bound
    assert "no more than on null data" in record["sentence"]


def test_a_base_never_calibrated_is_held_to_the_largest_bound_of_any_base():
    uncalibrated = predictable.null_gain_bounds("an engine nobody calibrated")
    assert set(uncalibrated) == set(predictable.STATISTICS)
    for name, bound in uncalibrated.items():
        assert bound == max(bounds[name] for bounds in predictable.NULL_GAIN_BOUNDS.values())
    for label, bounds in predictable.NULL_GAIN_BOUNDS.items():
        assert set(bounds) == set(predictable.STATISTICS), label
        assert predictable.null_gain_bounds(label) == bounds


def test_a_correction_is_judged_against_the_null_bounds_of_the_base_it_corrects():
    assert Hypothesis(1).law == "mujoco"
    for engine_name in ("bullet", "drake"):
        for option in engine_bases(engine_name, 1, 0):
            label = Hypothesis(1, base=option).law
            assert label == option.label and label in predictable.NULL_GAIN_BOUNDS  # every base is calibrated
