"""SysID through MJX (model=sysid_mjx): box coordinates, the forward-mode gradient against finite differences, descent
that lowers the C-MuJoCo val loss, the numbers-only checkpoint, and the pipeline at budget=smoke; on the hinged real
elbow, MJX's rollout against C MuJoCo's, the gradient in the joint damping and the pipeline."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from test_pipeline import compose_config
from test_sysid import TRUE_PARAMETERS, mujoco_made_cube  # noqa: F401 (a fixture)

from contactbench import metrics, runs
from contactbench.config import REPO_ROOT
from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.models.sysid.gradient import AdamThroughMjx, BoxCoordinates, MjxWindows, adam_step
from contactbench.models.sysid.objective import ConfigurationObjective
from contactbench.models.sysid.search_space import SearchSpace
from contactbench.recordings import read_recordings
from contactbench.sim import articulation, mjx
from contactbench.sim.mujoco_scene import world_velocities
from contactbench.sim.rollout import MujocoRollouts

ELBOW = REPO_ROOT / "assets" / "contactnets_elbow"


def test_box_coordinates_stay_in_the_domain_and_start_where_ngopt_does():
    space = SearchSpace(2)
    box = BoxCoordinates(space)
    start = space.from_vector(box.to_vector(box.start))
    assert start.object_friction == pytest.approx((0.5, 0.5)) and start.floor_friction == pytest.approx(0.5)
    assert start.floor_stiffness == pytest.approx(1e3) and start.floor_damping == pytest.approx(space.initial_damping)
    for far in (-1e3, 1e3):
        vector = box.to_vector(np.full(5, far))
        assert np.all(vector >= [0, 0, 0, 1e2 * (1 - 1e-12), 0]) and np.all(
            vector <= np.array([1, 1, 1, 1e4, 1e3]) * (1 + 1e-12)
        )
    vector = np.array([0.2, 0.7, 0.4, 3000.0, 80.0])
    np.testing.assert_allclose(box.to_vector(box.to_coordinates(vector)), vector, rtol=1e-9)


@pytest.mark.slow
def test_the_mjx_gradient_is_the_losss_slope_and_descent_lowers_the_c_mujoco_val_loss(mujoco_made_cube):  # noqa: F811
    """On tosses MuJoCo made with known parameters: jax.jacfwd through MJX agrees with central differences of the
    same loss, and a few Adam steps from NGOpt's start lower the C-MuJoCo val objective toward the true friction."""
    dataset, rollouts = mujoco_made_cube
    space = SearchSpace(1)
    windows = MjxWindows(dataset, space, context_frames=6, window_frames=8, position_exponent=2)
    batch = windows.windows(dataset.split("train"), dataset.dt, 8, np.random.default_rng(0))
    start = windows.coordinates.start
    loss, gradient = windows.value_and_gradient(start, batch)
    assert np.isfinite(loss) and np.isfinite(gradient).all()
    step = 1e-4
    for i in (0, 1, 2):  # frictions and stiffness: the gradient the docs report within ~5 % of differences
        shift = np.eye(4)[i] * step
        slope = (
            windows.value_and_gradient(start + shift, batch)[0] - windows.value_and_gradient(start - shift, batch)[0]
        ) / (2 * step)
        assert gradient[i] == pytest.approx(slope, rel=0.1, abs=1e-4 * abs(loss))
    val = ConfigurationObjective(dataset, "val", 6, rollouts, position_exponent=2)
    before = val([space.from_vector(windows.coordinates.to_vector(start))]).losses[0]
    coordinates, moments = start.copy(), (np.zeros(4), np.zeros(4))
    for k in range(12):
        batch = windows.windows(dataset.split("train"), dataset.dt, 8, np.random.default_rng([0, k]))
        coordinates, moments = adam_step(
            coordinates, moments, windows.value_and_gradient(coordinates, batch)[1], 0.1, k
        )
    found = space.from_vector(windows.coordinates.to_vector(coordinates))
    assert val([found]).losses[0] < 0.8 * before
    assert abs(found.object_friction[0] - 0.3) < abs(0.5 - 0.3)  # the data's object friction, 0.3, beats the floor's


def test_the_descent_checkpoint_holds_numbers_only_and_refuses_anything_else():
    callback = AdamThroughMjx()
    callback.coordinates = np.zeros(4)
    callback.moments = (np.zeros(4), np.ones(4))
    state = callback.state_dict()
    AdamThroughMjx().load_state_dict(state)
    for field, value, message in (
        ("step", -1, "field 'step' is -1"),
        ("coordinates", torch.tensor([np.nan] * 4, dtype=torch.float64), "field 'coordinates'"),
        ("first_moment", torch.zeros(3, dtype=torch.float64), "field 'first_moment'"),
        ("seconds", {"compile": 1.0}, "field 'seconds'"),
        ("optimizer", b"\x80\x04", "field 'optimizer' is not part of the descent state"),
    ):
        with pytest.raises(ContactbenchError, match=message):
            AdamThroughMjx().load_state_dict(state | {field: value})


@pytest.mark.slow
def test_sysid_mjx_runs_the_pipeline_and_selects_on_val(tmp_path):
    cfg = compose_config("train", ["dataset=contactnets_cube", "model=sysid_mjx", "budget=smoke"], tmp_path)
    run_dir = tmp_path / "run"
    runs.train(cfg, run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    assert set(fitted["parameters"]) == set(SearchSpace(1).names)  # sysid's: fitted.json reads the same
    with open(run_dir / "csv" / "metrics.csv") as rows:
        val_losses = [float(row["val/loss"]) for row in csv.DictReader(rows) if row["val/loss"]]
    assert fitted["val_loss"] == pytest.approx(min(val_losses), rel=1e-6)  # the CSV holds float32
    assert min(val_losses) <= val_losses[0]  # the start (NGOpt's) is a candidate too
    metrics = json.loads((run_dir / "val" / "metrics.json").read_text())
    assert metrics["model"] == "sysid_mjx" and np.isfinite(metrics["pos_err"])


# ---------------------------------------------------------------- hinged scenes: the real elbow


def test_box_coordinates_cover_a_hinged_scenes_articulation_and_start_inside_it():
    space = SearchSpace(2, 1)
    box = BoxCoordinates(space)
    hinges = articulation.dimensions(1)
    assert len(box.start) == len(space.names) == 5 + len(hinges)
    assert list(box.logarithmic) == [name in ("floor_stiffness", "inertia_scale") for name in space.names]
    start = space.from_vector(box.to_vector(box.start))
    assert start.floor_damping == pytest.approx(space.initial_damping)  # the contact dimensions start as before
    damping, friction, inertia = hinges
    # NGOpt starts joint damping and friction at 0, a bound where the sigmoid passes no gradient: just inside it
    assert start.articulation.joint_damping[0] == pytest.approx(damping.low + 0.05 * (damping.high - damping.low))
    assert start.articulation.joint_friction[0] == pytest.approx(friction.low + 0.05 * (friction.high - friction.low))
    assert start.articulation.inertia_scale == pytest.approx(1.0)
    for far in (-1e3, 1e3):
        vector = box.to_vector(np.full(len(box.start), far))
        assert np.all(vector[5:] >= np.array([d.low for d in hinges]) * (1 - 1e-12))
        assert np.all(vector[5:] <= np.array([d.high for d in hinges]) * (1 + 1e-12))
    vector = np.array([0.2, 0.3, 0.7, 3000.0, 80.0, 0.3 * damping.high, 0.6 * friction.high, 1.7])
    np.testing.assert_allclose(box.to_vector(box.to_coordinates(vector)), vector, rtol=1e-9)


def test_scenes_mjx_refuses_are_not_applicable_in_one_line(monkeypatch):
    scene = read_recordings(ELBOW, splits=["val"]).scene
    mjx.require_mjx(scene)  # a hinge, convex bars: MJX takes it

    def refuse(model):
        raise NotImplementedError("Geom type HFIELD with\nMESH is not implemented")

    monkeypatch.setattr("mujoco.mjx.put_model", refuse)
    with pytest.raises(NotApplicable, match=r"^MJX cannot simulate contactnets-elbow's MuJoCo model: Geom type HFIELD"):
        mjx.require_mjx(scene)


@pytest.fixture(scope="module")
def elbow_windows():
    """The real elbow, MJX's windows of 8 frames (one compile of each jit for the tests below) and 3 train windows:
    in flight for their first frames, then landing."""
    dataset = read_recordings(ELBOW)
    space = SearchSpace(dataset.n_bodies, len(dataset.joints))
    windows = MjxWindows(dataset, space, context_frames=6, window_frames=8, position_exponent=2)
    batch = windows.windows(dataset.split("train"), dataset.dt, 3, np.random.default_rng(0))
    hinges = [d.high for d in articulation.dimensions(1)]
    vector = np.array([0.4, 0.4, 0.6, 3000.0, 80.0, 0.4 * hinges[0], 0.2 * hinges[1], 1.6])
    return dataset, space, windows, batch, windows.coordinates.to_coordinates(vector)


@pytest.mark.slow
def test_mjx_rolls_the_hinged_elbow_out_as_c_mujoco_does(elbow_windows):
    """From the same states with the same contact, hinge and inertia parameters: in flight MJX's poses are C MuJoCo's
    (to rounding: the same dynamics, hinge damping, friction loss and scaled inertia, read from MJX's body frames); once
    a bar lands they part by what MJX's mesh-plane contacts do differently (up to 4 points where C has 3:
    docs/DIFFERENTIABLE.md measured this on the real cube), bounded here over a few frames."""
    dataset, space, windows, batch, coordinates = elbow_windows
    parameters = space.from_vector(windows.coordinates.to_vector(coordinates))
    predicted = windows.poses(coordinates, batch)
    rollouts = MujocoRollouts(dataset.scene, nthread=1)
    poses, velocities = rollouts.layout.unpack(batch[0], batch[1])
    simulated = rollouts.simulate(parameters, poses, world_velocities(poses, velocities), 8).poses[0]
    heights = metrics.lowest_vertex_height(simulated, [dataset.body_mesh(k) for k in range(2)], dataset.floor_z)
    flying = np.cumprod(heights.min(axis=-1) > 1e-3, axis=-1).astype(bool)  # before any bar nears the floor
    assert flying.sum() >= 3 and not flying.all()
    gap = np.linalg.norm(predicted[..., :3] - simulated[..., :3], axis=-1)
    angle = metrics.rotation_error(simulated, predicted)
    assert gap[flying].max() < 1e-9 and angle[flying].max() < 1e-6
    assert gap.max() < 2e-3 and angle.max() < 0.03
    at_start = windows.poses(windows.coordinates.start, batch)  # the hinge parameters act in flight, well above that
    assert metrics.rotation_error(at_start, predicted)[flying].max() > 1e-4


@pytest.mark.slow
def test_the_gradient_reaches_the_joint_damping(elbow_windows):
    _, space, windows, batch, coordinates = elbow_windows
    loss, gradient = windows.value_and_gradient(coordinates, batch)
    assert np.isfinite(loss) and np.isfinite(gradient).all()
    damping = space.names.index("joint_damping_0")
    step = np.eye(len(coordinates))[damping] * 1e-3
    slope = (
        windows.value_and_gradient(coordinates + step, batch)[0]
        - windows.value_and_gradient(coordinates - step, batch)[0]
    ) / 2e-3
    assert gradient[damping] != 0 and gradient[damping] == pytest.approx(slope, rel=0.05)


@pytest.mark.slow
def test_sysid_mjx_runs_the_pipeline_on_the_hinged_elbow(tmp_path):
    cfg = compose_config("train", ["dataset=contactnets_elbow", "model=sysid_mjx", "budget=smoke"], tmp_path)
    run_dir = tmp_path / "run"
    runs.train(cfg, run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    assert list(fitted["parameters"]) == SearchSpace(2, 1).names
    assert {"joint_damping_0", "joint_friction_0", "inertia_scale"} <= set(fitted["parameters"])
    metrics_json = json.loads((run_dir / "val" / "metrics.json").read_text())
    assert metrics_json["model"] == "sysid_mjx" and np.isfinite(metrics_json["pos_err"])
