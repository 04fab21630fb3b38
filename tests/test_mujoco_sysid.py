"""model=mujoco_sysid, MuJoCo's own system-identification toolbox on sysid's problem: its residuals are eq. (1), it
finds friction it was shown, it runs through the pipeline, and every SysID run's fitted.json says how it was fitted."""

from __future__ import annotations

import json
from dataclasses import replace

import mujoco
import nevergrad as ng
import numpy as np
import pytest
import pytorch_lightning as pl
from test_pipeline import compose_config

from contactbench import runs
from contactbench.config import REPO_ROOT
from contactbench.errors import ContactbenchError
from contactbench.models.sysid.module import SysIDDataModule
from contactbench.models.sysid.mujoco_toolbox import LeastSquaresSearch, ToolboxSysIDModule, check_fit_state
from contactbench.models.sysid.objective import ConfigurationObjective
from contactbench.models.sysid.uncertainty import EquationOneResiduals
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.sim.mujoco_scene import ContactParameters
from contactbench.sim.rollout import MujocoRollouts

# MuJoCo takes the larger of the object's and the floor's friction: 0.3 is the friction these tosses slide with.
TRUE_PARAMETERS = ContactParameters(
    object_friction=(0.3,), floor_friction=0.05, floor_stiffness=2000.0, floor_damping=60.0
)
SMALL = ["budget=smoke", "dataset=frictioncubes", "friction=0.5", "generation.split_sizes={train:6,val:4,test:4}"]


@pytest.fixture(scope="module")
def mujoco_made_cube():
    """Real cube tosses re-simulated in MuJoCo with known parameters: the toolbox's model class made them."""
    real = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["train", "val"])
    rollouts = MujocoRollouts(real, nthread=2)
    splits = {}
    for name, count in (("train", 16), ("val", 8)):
        recorded = real.split(name).select(range(count))
        context = make_context(recorded, real.dt, 6)
        simulated = rollouts.rollout_context(context, TRUE_PARAMETERS)
        after_end = np.arange(context.horizon)[None, :, None, None] >= recorded.lengths[:, None, None, None]
        poses = np.where(after_end, np.nan, simulated.poses[0])
        velocities = np.where(after_end, np.nan, simulated.velocities[0])
        splits[name] = replace(recorded, poses=poses, velocities=velocities, extras={})
    return replace(real, splits=splits), rollouts


@pytest.fixture(scope="module")
def small_data(tmp_path_factory):
    """Where a small frictioncubes variant is generated once for the pipeline runs of this file."""
    return tmp_path_factory.mktemp("small")


def test_the_residuals_sum_of_squares_is_the_sysid_objective(mujoco_made_cube):
    dataset, rollouts = mujoco_made_cube
    residuals = EquationOneResiduals(dataset, "train", 6, rollouts, position_exponent=2)
    objective = ConfigurationObjective(dataset, "train", 6, rollouts, position_exponent=2)
    candidates = [
        TRUE_PARAMETERS,
        replace(TRUE_PARAMETERS, object_friction=(0.6,)),
        replace(TRUE_PARAMETERS, floor_damping=5.0),
    ]
    values, unstable = residuals(candidates)
    assert values.shape == (3, residuals.size) and not unstable.any()
    np.testing.assert_allclose((values**2).sum(axis=1), objective(candidates).losses, rtol=1e-9, atol=1e-12)
    assert (values[0] ** 2).sum() < 1e-12 < (values[1] ** 2).sum()
    exploding, diverged = residuals([replace(TRUE_PARAMETERS, floor_stiffness=100.0, floor_damping=1000.0)])
    assert diverged[0] and (exploding**2).sum() == pytest.approx(1000.0)  # the flat penalty, as sysid's objective gives


def test_it_recovers_the_friction_that_made_the_data(mujoco_made_cube, tmp_path):
    """From a start of 0.5, the toolbox's least squares finds the 0.3 the tosses were simulated with, and says how
    sure it is: a finite interval around it, none for the floor's friction, which the larger object's hides."""
    dataset, rollouts = mujoco_made_cube
    module = ToolboxSysIDModule(
        dataset,
        context_frames=6,
        restarts=1,
        max_iters=15,
        train_trajectories=None,
        val_trajectories=None,
        nthread=2,
    )
    trainer = pl.Trainer(
        max_epochs=-1,
        limit_val_batches=0,
        enable_checkpointing=False,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[LeastSquaresSearch()],
        default_root_dir=str(tmp_path),
    )
    trainer.fit(module, datamodule=SysIDDataModule(dataset, 6, generations=1), weights_only=True)
    summary = module.fitted_summary()
    friction = summary["uncertainty"]["parameters"]["object_friction_0"]
    assert abs(friction["value"] - 0.3) < 0.02, summary["parameters"]
    assert friction["unit"] == "1" and friction["interval"][0] <= friction["value"] <= friction["interval"][1]
    assert summary["uncertainty"]["parameters"]["floor_friction"]["interval"] is None
    assert summary["uncertainty"]["parameters"]["floor_stiffness"]["unit"] == "1/s^2"
    start = ConfigurationObjective(dataset, "train", 6, rollouts, position_exponent=2)
    at_start = start([module.space.from_vector([0.5, 0.05, 1000.0, 50.0])]).losses[0]
    assert summary["train_loss"] < at_start / 10, (summary["train_loss"], at_start)
    assert summary["optimizer"]["name"] == "mujoco.sysid.optimize" and summary["optimizer"]["iterations"] >= 1
    assert summary["versions"]["mujoco"] == mujoco.__version__


def test_mujoco_sysid_runs_end_to_end_and_fitted_json_carries_the_uncertainty(small_data):
    cfg = compose_config("train", ["model=mujoco_sysid", *SMALL, "test=true"], small_data)
    run_dir = small_data / "mujoco_sysid"
    val_pos_err = runs.train(cfg, run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    names = ["object_friction_0", "floor_friction", "floor_stiffness", "floor_damping"]
    assert fitted["model"] == "mujoco_sysid" and list(fitted["parameters"]) == names
    uncertainty = fitted["uncertainty"]
    assert uncertainty["confidence"] == 0.95 and list(uncertainty["parameters"]) == names
    for name, entry in uncertainty["parameters"].items():
        assert entry["value"] == fitted["parameters"][name] and entry["unit"]
        assert entry["interval"] is None or entry["interval"][0] <= entry["value"] <= entry["interval"][1]
    assert fitted["covariance"]["names"] == names and len(fitted["covariance"]["matrix"]) == 4
    assert fitted["optimizer"]["backend"] == "mujoco" and set(fitted["versions"]) == {"mujoco", "scipy"}
    assert 0 < val_pos_err < 5 and (run_dir / "test" / "metrics.json").is_file()
    evaluated = runs.evaluate(
        compose_config("evaluate", ["model=mujoco_sysid", *SMALL[:3], f"train_dir={run_dir}", "split=val"], small_data),
        small_data / "mujoco_sysid_evaluated",
    )
    assert evaluated["pos_err"] == pytest.approx(val_pos_err)


def test_sysid_fitted_json_names_the_optimiser_ngopt_chose_and_the_versions(small_data):
    cfg = compose_config("train", ["model=sysid", *SMALL], small_data)
    run_dir = small_data / "sysid"
    runs.train(cfg, run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    optimizer = fitted["optimizer"]
    assert optimizer["name"] == "NGOpt" and len(optimizer["chosen"]) == cfg.model.module.restarts
    # NGOpt is a wizard: what it ran is one of nevergrad's own optimisers, never itself
    assert all(choice and not choice.startswith("NGOpt") for choice in optimizer["chosen"]), optimizer
    assert fitted["versions"] == {"nevergrad": ng.__version__, "mujoco": mujoco.__version__}


def test_bad_settings_and_checkpoint_states_are_one_clear_line(mujoco_made_cube):
    dataset, _ = mujoco_made_cube
    settings = {"context_frames": 6, "restarts": 1, "max_iters": 2, "train_trajectories": 4, "val_trajectories": 4}
    refused = (({"optimizer": "lbfgs"}, "model.module.optimizer is 'lbfgs'"), ({"max_iters": 0}, "max_iters is 0"))
    for bad, expected in refused:
        with pytest.raises(ContactbenchError, match=expected) as error:
            ToolboxSysIDModule(dataset, **{**settings, **bad})
        assert len(str(error.value).splitlines()) == 1
    with pytest.raises(ContactbenchError, match="results\\[0\\] is malformed"):
        check_fit_state({"results": [{"vector": [0.1]}]}, "a checkpoint")
    with pytest.raises(ContactbenchError, match="expected"):
        check_fit_state({"optimizer": b"pickled"}, "a checkpoint")
