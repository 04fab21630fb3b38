"""SysID through MJX (model=sysid_mjx): box coordinates, the forward-mode gradient against finite differences, descent
that lowers the C-MuJoCo val loss, the numbers-only checkpoint, and the pipeline at budget=smoke."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from test_pipeline import compose_config
from test_sysid import TRUE_PARAMETERS, mujoco_made_cube  # noqa: F401 (a fixture)

from contactbench import runs
from contactbench.errors import ContactbenchError
from contactbench.models.sysid.gradient import AdamThroughMjx, BoxCoordinates, MjxWindows, adam_step
from contactbench.models.sysid.objective import ConfigurationObjective
from contactbench.models.sysid.search_space import SearchSpace


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
