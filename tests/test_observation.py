"""Tests of how a dataset is observed (noise, frame stride), the fitted context velocities, the sensitivity study."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import falling_cubes
from test_pipeline import compose_config, run_entry_point

from contactbench import rotations, runs
from contactbench.config import REPO_ROOT
from contactbench.errors import ContactbenchError
from contactbench.evaluation.report import write_report
from contactbench.evaluation.scoring import score_model
from contactbench.kinematics import estimate_velocities, fit_velocities
from contactbench.models.analytical import MujocoContactModel
from contactbench.observation import Observation
from contactbench.recordings import read_recordings, write_recordings


def test_plain_observation_changes_no_number_of_the_benchmark(tmp_path):
    document = runs.evaluate(
        compose_config("evaluate", ["dataset=contactnets_cube", "model=mujoco_default"], tmp_path), tmp_path / "run"
    )
    dataset = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["test"])
    plain = score_model(
        MujocoContactModel("mujoco_default", preset="mujoco_default"),
        dataset,
        "test",
        6,
        dataset_name="contactnets_cube",
        variant="real",
    ).summary()
    for key in ("pos_err", "rot_err_rad", "floor_penetration_m", "scored_frames"):
        assert document[key] == plain[key]
    assert document["noise_mm"] == 0 and document["frame_stride"] == 1
    assert document["scored_against"] == "observed recording"


def test_an_observation_is_deterministic_thins_frames_and_adds_the_stated_noise():
    dataset = falling_cubes(n_trajectories=40, n_frames=21, seed=1)
    observation = Observation(noise_mm=2.0, frame_stride=2, seed=5)
    first, second = observation.observe(dataset), observation.observe(dataset)
    other_seed = Observation(noise_mm=2.0, frame_stride=2, seed=6).observe(dataset)
    clean = observation.clean(dataset)
    for name in ("train", "val"):
        assert np.array_equal(first.split(name).poses, second.split(name).poses)
    assert not np.array_equal(first.split("train").poses, other_seed.split("train").poses)
    assert not np.array_equal(first.split("train").poses, first.split("val").poses)  # each split its own draw
    assert first.dt == clean.dt == 2 * dataset.dt
    assert np.array_equal(first.split("train").lengths, np.full(40, 11))
    assert np.array_equal(clean.split("train").poses, dataset.split("train").poses[:, ::2])
    assert first.split("train").velocities is None  # a tracker does not measure them
    assert clean.split("train").velocities is not None
    offsets = first.split("train").poses[..., :3] - clean.split("train").poses[..., :3]
    assert abs(offsets.std() - 2e-3) < 1e-4
    angles = rotations.angle_between(first.split("train").poses[..., 3:], clean.split("train").poses[..., 3:])
    per_component = 2e-3 / (dataset.widths()[0] / 2)
    # The angle of a rotation vector with three N(0, s^2) components has mean s * 2 sqrt(2 / pi).
    assert abs(angles.mean() / (per_component * 2 * np.sqrt(2 / np.pi)) - 1) < 0.05
    with pytest.raises(ContactbenchError, match="observation.frame_stride is 0"):
        Observation(frame_stride=0)


def test_fitted_context_velocities_are_exact_without_noise_and_robust_with_it():
    dataset = falling_cubes(n_trajectories=200, n_frames=6, seed=2)
    split = dataset.split("train")
    assert np.abs(fit_velocities(split.poses, dataset.dt) - split.velocities).max() < 1e-10
    at_rest = np.broadcast_to(split.poses[:, :1], split.poses.shape)
    assert np.abs(fit_velocities(at_rest, dataset.dt)).max() < 1e-10
    noisy = Observation(noise_mm=1.0, seed=0).observe(dataset).split("train").poses
    errors = {
        name: estimator(noisy, dataset.dt)[:, -1] - split.velocities[:, -1]
        for name, estimator in (("backward", estimate_velocities), ("fitted", fit_velocities))
    }
    rms = {name: np.sqrt((error**2).mean(axis=(0, 1))) for name, error in errors.items()}
    assert (rms["fitted"][:3] < 0.7 * rms["backward"][:3]).all()  # linear
    assert (rms["fitted"][3:] < 0.3 * rms["backward"][3:]).all()  # angular


class Oracle(MujocoContactModel):
    """Returns the clean recording itself: zero error against it, the noise's size against the noisy one."""

    def __init__(self, clean):
        super().__init__("oracle", preset="mujoco_default")
        self.clean = clean

    def rollout(self, scene, context):
        return self.clean.poses[:, : context.horizon]


def test_synthetic_data_are_scored_against_the_clean_recording(tmp_path):
    folder = write_recordings(tmp_path / "cubes", falling_cubes(n_trajectories=6, n_frames=30, seed=4))
    overrides = ["dataset=recordings", f"recordings={folder}", "model=mujoco_default", "split=test"]
    observed_overrides = [*overrides, "observation.noise_mm=3", "observation.frame_stride=2"]
    observed = runs.load_dataset(compose_config("evaluate", observed_overrides, tmp_path), ["test"])
    clean = Observation(frame_stride=2).clean(read_recordings(folder, ["test"])).split("test")
    assert observed.observation == {"noise_mm": 3.0, "frame_stride": 2, "scored_against": "clean recording"}
    assert np.array_equal(observed.truth.split("test").poses, clean.poses)
    assert not np.allclose(observed.dataset.split("test").poses, clean.poses)
    oracle = Oracle(clean)
    against_clean = score_model(oracle, observed.dataset, "test", 6, dataset_name="c", variant="v", truth=clean)
    against_noisy = score_model(oracle, observed.dataset, "test", 6, dataset_name="c", variant="v")
    assert against_clean.metrics.summary["pos_err"] == 0.0
    assert against_noisy.metrics.summary["pos_err"] > 0.03  # about 3 mm x sqrt(3) on a 10 cm cube
    documents = [
        runs.evaluate(compose_config("evaluate", observed_overrides, tmp_path), tmp_path / name)
        for name in ("first", "second")
    ]
    for document in documents:
        document.pop("rollout_seconds")  # the only thing measured, not computed
    assert json.dumps(documents[0], sort_keys=True) == json.dumps(documents[1], sort_keys=True)  # same seed
    assert documents[0]["scored_against"] == "clean recording"


def test_the_sensitivity_experiment_runs_and_the_report_draws_it(tmp_path):
    sweep = tmp_path / "sweep"
    result = run_entry_point(
        "train.py",
        [
            "-m",
            "experiment=sensitivity",
            "budget=smoke",
            "model=mujoco_default",
            "variant=contactnets_cube",
            "observation.noise_mm=0,2",
            "observation.frame_stride=1,2",
            f"hydra.sweep.dir={sweep}",
        ],
        tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert len(list(sweep.rglob("test/metrics.json"))) == 4
    text = write_report(sweep, renders=False).read_text()
    assert "## Sensitivity to tracking noise and frame rate" in text
    assert "| 2 | 2 |" in text and "mujoco_default:" in text
    figures = sorted(path.name for path in (sweep / "figures").glob("sensitivity_*.png"))
    assert figures == [
        "sensitivity_frame_stride_contactnets_cube_real.png",
        "sensitivity_noise_mm_contactnets_cube_real.png",
    ]
