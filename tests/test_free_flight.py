"""diagnosis.free_flight: the model-free checks of free flight (the fall against meta.gravity, a drag), and the
simulator's drag in the same units (diagnosis.simulated_drag)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from contactbench.config import REPO_ROOT
from contactbench.diagnosis import free_flight, simulated_drag
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.recordings import read_recordings
from contactbench.sim.mujoco_scene import ContactParameters, SceneEffects, build_model

CUBE = SceneSpec("frictioncubes", friction=0.5, restitution=0.0)
SIZES = {"train": 10, "val": 10, "test": 10}


def test_a_concealed_weaker_gravity_is_measured_in_free_flight_and_a_null_dataset_is_consistent(tmp_path):
    rng = np.random.default_rng(0)
    null = read_recordings(generate_dataset(CUBE, tmp_path / "null", split_sizes=SIZES, workers=1, progress=False))
    weak = read_recordings(
        generate_dataset(
            CUBE, tmp_path / "weak", split_sizes=SIZES, workers=1, progress=False, effects=("gravity_scale",)
        )
    )
    assert weak.meta["gravity"] == null.meta["gravity"]  # concealed: meta keeps 9.8
    found = free_flight.check(weak.for_models(list(weak.splits)), rng, draws=200)
    assert found["scale"] == pytest.approx(1 / 1.05, abs=2e-3)
    assert found["differs"] and found["confirmed"]
    assert found["frame_interval_factor"] == pytest.approx(np.sqrt(1 / 1.05), abs=1e-3)
    for part in found["splits"].values():
        assert part["n_frames"] > 50 and abs(part["acceleration"][0]) < 0.05 and abs(part["acceleration"][1]) < 0.05
        assert part["along_gravity_ci95"][1] < 9.8
    assert "differs on val, confirmed on test" in found["sentence"]
    plain = free_flight.check(null.for_models(list(null.splits)), rng, draws=200)
    assert plain["scale"] == pytest.approx(1.0, abs=2e-3) and not plain["differs"] and not plain["confirmed"]
    assert "consistent with meta" in plain["sentence"]


def test_a_concealed_air_drag_is_measured_in_free_flight_and_the_fall_net_of_it_stays_at_gravity(tmp_path):
    rng = np.random.default_rng(0)
    dragged = read_recordings(
        generate_dataset(CUBE, tmp_path / "drag", split_sizes=SIZES, workers=1, progress=False, effects=("air_drag",))
    )
    found = free_flight.check(dragged.for_models(list(dragged.splits)), rng, draws=200)
    assert found["drag_measured"] and found["drag_confirmed"] and not found["apparent_gravity"]
    for part in found["splits"].values():
        # A body slows against its motion (k > 0), and the fall net of the drag is still meta.gravity's.
        assert part["drag_ci95"][0] > 0 and part["drag_deceleration_m_s2"] > 0.3
        assert part["scale"] == pytest.approx(1.0, abs=0.01)
    assert "a drag (still or moving air)" in found["sentence"]
    null = read_recordings(generate_dataset(CUBE, tmp_path / "null", split_sizes=SIZES, workers=1, progress=False))
    plain = free_flight.check(null.for_models(list(null.splits)), rng, draws=200)
    assert not plain["drag_measured"] and abs(plain["splits"]["val"]["drag_deceleration_m_s2"]) < 1e-6
    # exact ballistic flight rules out both a drag and an apparent gravity
    assert plain["drag_evidence"] == plain["gravity_evidence"] == free_flight.RULED_OUT
    assert "a drag is ruled out" in plain["sentence"]
    assert found["drag_evidence"] == free_flight.MEASURED


def test_free_frames_leave_out_contact_and_the_ends(tmp_path):
    data = read_recordings(
        generate_dataset(CUBE, tmp_path / "null", split_sizes={"train": 4}, workers=1, progress=False)
    )
    split = data.split("train")
    free = free_flight.free_frames(data, split)
    assert not free[:, 0].any() and not free[:, -1].any()
    assert free.any() and not (free & ~(split.poses[..., 2] > data.widths()[0] * free_flight.CLEARANCE)).any()


def test_the_simulated_drag_is_mujocos_box_drag_and_is_compared_with_the_measured_one():
    real = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", splits=["val"])
    base = ContactParameters.mujoco_default(1)

    def k(density):
        parameters = dataclasses.replace(base, effects=SceneEffects(fluid_density=density, wind=(2.0, 0.0, 0.0)))
        return simulated_drag.drag_per_metre(real, parameters, np.random.default_rng(0))

    # the equivalent box of a cube's inertia: side^2 = 6 I / m; along a face normal F = rho side^2 v^2 / 2, and
    # along any other direction u the drag on it is that times sum |u_i|^3, between 1/sqrt(3) and 1
    mass, inertia = build_model(real, base).body_mass[1], real.inertial(0)[1][0, 0]
    along_a_face = 1.2 * 6 * inertia / mass / (2 * mass)
    still = k(1.2)
    assert along_a_face / np.sqrt(3) - 1e-9 <= still["range"][0] < still["k_per_m"] < still["range"][1] <= along_a_face
    assert k(12.0)["k_per_m"] == pytest.approx(10 * still["k_per_m"])  # quadratic drag scales with the density
    assert k(0.0)["k_per_m"] == 0.0
    measured = {"drag_per_m": 0.037, "drag_ci95": [0.015, 0.063]}
    assert simulated_drag.against_free_flight(still, measured)["consistent"]
    strong = simulated_drag.against_free_flight(k(6.94), measured)
    assert not strong["consistent"] and strong["ratio"] > 2


def test_velocities_of_another_convention_are_measured_and_aligned_and_the_engines_own_are_left_alone(tmp_path):
    # An engine stepping several times a frame stores v_t = (x_t - x_{t-1}) / dt + c g dt in free flight; the one-step
    # semi-implicit convention the simulators restart from has c = 0.
    from contactbench.diagnosis import velocities

    null = read_recordings(generate_dataset(CUBE, tmp_path / "null", split_sizes=SIZES, workers=1, progress=False))
    null = null.for_models(list(null.splits))
    plain = velocities.check(null, np.random.default_rng(0), draws=200)
    assert not plain["aligned"] and velocities.aligned(null, plain) is null
    lead = np.array([0.0, 0.0, -3 / 7 * 9.8 * null.dt, 0.0, 0.0, 0.0])
    shifted = dataclasses.replace(
        null,
        splits={name: dataclasses.replace(s, velocities=s.velocities + lead) for name, s in null.splits.items()},
    )
    found = velocities.check(shifted, np.random.default_rng(0), draws=200)
    assert found["aligned"] and found["offset"] == pytest.approx(lead[:3], abs=1e-9)
    restored = velocities.aligned(shifted, found)
    for name, split in restored.splits.items():
        assert np.allclose(split.velocities, null.split(name).velocities, atol=1e-9)
    assert "differ from the backward differences" in found["sentence"]


ELBOW = SceneSpec("articulated", friction=0.3, restitution=0.125, shape="elbow", bodies=2)


def test_a_hinged_pair_falls_at_g_at_its_centre_of_mass_and_a_slow_clock_shows_there(tmp_path):
    # Two links on a hinge: the hinge force swings each link's centre of mass off the parabola, the pair's
    # mass-weighted centre of mass stays on it.
    elbow = read_recordings(generate_dataset(ELBOW, tmp_path / "elbow", split_sizes=SIZES, workers=1, progress=False))
    elbow = elbow.for_models(list(elbow.splits))
    found = free_flight.check(elbow, np.random.default_rng(0), draws=200)
    g = np.linalg.norm(elbow.gravity)
    for part in found["splits"].values():
        assert part["n_trajectories"] >= 3 and part["n_frames"] > 30
        assert part["scale"] == pytest.approx(1.0, abs=free_flight.MARGIN)
    assert not found["differs"] and found["gravity_evidence"] == free_flight.RULED_OUT
    split = elbow.split("train")
    free = free_flight.free_frames(elbow, split)
    assert free.any() and (free[..., 0] == free[..., 1]).all()  # a tree flies as one
    _, body = free_flight.centre_motion(elbow, split)
    _, pair = free_flight.system_motion(elbow, split)
    each = np.median(np.linalg.norm(body[free[..., 0]] - elbow.gravity, axis=-1), axis=0)  # per link
    both = np.median(np.linalg.norm(pair[free[..., 0]][:, 0] - elbow.gravity, axis=-1))
    assert (each > free_flight.MARGIN * g).all() and both < 0.1 * free_flight.MARGIN * g
    # The same tosses recorded with a frame interval sqrt(1.05) times the true one: an apparent gravity g / 1.05.
    slow = dataclasses.replace(elbow, meta={**elbow.meta, "dt": elbow.dt * np.sqrt(1.05)})
    found = free_flight.check(slow, np.random.default_rng(0), draws=200)
    assert found["scale"] == pytest.approx(1 / 1.05, abs=2e-3)
    assert found["differs"] and found["confirmed"] and found["apparent_gravity"]


def test_the_real_elbow_is_seen_in_free_flight_on_every_split_and_falls_near_g():
    elbow = read_recordings(REPO_ROOT / "assets" / "contactnets_elbow")
    elbow = elbow.for_models(list(elbow.splits))
    found = free_flight.check(elbow, np.random.default_rng(0), draws=200)
    for part in found["splits"].values():
        assert part["n_trajectories"] > 50 and part["n_frames"] > 1000
    assert found["scale"] == pytest.approx(1.0, abs=0.05)
    assert "Too few" not in found["sentence"]
    # The publisher's velocities are backward differences; the free frames are picked stretch by stretch, so the
    # tracking noise of a frame does not pick which frames count, and no offset is made up.
    from contactbench.diagnosis import velocities

    assert not velocities.check(elbow, np.random.default_rng(0), draws=200)["aligned"]
