"""The console carries this run's news only: no third-party chatter (seeds, accelerators, deprecations, build dates),
and a long fit says where it is, one line per validation in a log, a bar over the whole fit at a terminal."""

from __future__ import annotations

import logging
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest
from test_pipeline import compose_config, run_entry_point

from contactbench import fitting, rotations
from contactbench.config import REPO_ROOT
from contactbench.models import progress
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings

NOISE = (
    "Seed set to",
    "GPU available",
    "TPU available",
    "configure_optimizers",
    "LeafSpec",
    "_pytree",
    "pybullet build time",
    "`Trainer.fit` stopped",
    "RuntimeWarning",
    "Warning:",
)


def chatter(text: str) -> list[str]:
    return [line for line in text.splitlines() if any(noise in line for noise in NOISE)]


@pytest.mark.slow
def test_a_gnn_fit_in_a_log_says_setting_and_step_at_every_validation_and_nothing_else(tmp_path):
    run = tmp_path / "run"
    done = run_entry_point(
        "train.py", ["model=gnn", "dataset=contactnets_cube", "budget=smoke", f"hydra.run.dir={run}"], tmp_path
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert not chatter(done.stdout + done.stderr), chatter(done.stdout + done.stderr)
    log = (run / "train.log").read_text()
    # budget=smoke: three noise settings, 20 steps each, validated every 10
    lines = re.findall(r"gnn setting (\d)/3 \(noise_std=[\d.e-]+\), step (\d+)/20: val/pos_err [\d.]+", log)
    assert [(int(k), int(step)) for k, step in lines] == [(k, s) for k in (1, 2, 3) for s in (10, 20)], log


@pytest.mark.slow
def test_a_sysid_fit_and_a_generated_dataset_print_no_third_party_chatter(tmp_path):
    done = run_entry_point(
        "train.py",
        ["model=sysid", "variant=frictioncubes_0.5", "budget=smoke", "generation.split_sizes={train:6,val:4,test:4}"],
        tmp_path,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert not chatter(done.stdout + done.stderr), chatter(done.stdout + done.stderr)


def test_the_bar_names_the_setting_and_counts_steps_over_the_whole_fit():
    bar = progress.where("gnn", (2, 3, "noise_std=0.0002"), 500, 2500)
    assert bar == "gnn setting 2/3 (noise_std=0.0002), step 500/2500"
    assert progress.where("gnn", None, 7, 20) == "gnn step 7/20"
    assert progress.where("sysid", None, 3, None) == "sysid step 3"


def test_the_fitting_code_tells_the_progress_callback_which_setting_it_fits(tmp_path):
    cfg = compose_config("train", ["model=gnn", "budget=smoke"], tmp_path)
    candidates = fitting.settings_grid(cfg.model.choose_on_val)
    setting = (3, len(candidates), fitting.setting_name(candidates[2]))
    trainer = fitting.make_trainer(cfg, cfg.model, tmp_path / "checkpoints", tmp_path, None, setting)
    (shown,) = [callback for callback in trainer.callbacks if isinstance(callback, progress.FitProgress)]
    assert shown.setting == (3, 3, "noise_std=0.0004")
    assert progress.label("gnn", shown.setting) == "gnn setting 3/3 (noise_std=0.0004)"


def test_pybullet_is_imported_without_its_build_time_line():
    probe = (
        "from contactbench.sim.quiet_pybullet import pybullet; pybullet.disconnect(pybullet.connect(pybullet.DIRECT))"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout == "" and done.stderr == "", done.stdout + done.stderr


def test_a_drake_world_with_a_floor_builds_without_drake_s_deformable_contact_warning(caplog):
    from contactbench.sim.drake_engine import DrakeEngine, DrakeWorld

    dataset = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["val"])
    context = make_context(dataset.split("val").select(np.arange(1)), dataset.dt, 6)
    parameters = DrakeEngine().default_parameters(dataset.n_bodies)
    with caplog.at_level(logging.INFO, logger="drake"):
        poses, _ = DrakeWorld(dataset.scene).toss(parameters, context.poses[0, -1], context.velocities[0, -1], 2)
    assert np.isfinite(poses).all()
    assert not [record for record in caplog.records if "half spaces" in record.getMessage()]


def test_a_zero_quaternion_normalises_to_nan_without_a_warning():
    """Zero-filled frames past a toss's end have no orientation: NaN, not a RuntimeWarning on the console."""
    q = np.array([[0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        normalized = rotations.normalize(q)
        matrices = rotations.to_matrix(q)
    assert np.isnan(normalized[0]).all() and np.array_equal(normalized[1], [1.0, 0.0, 0.0, 0.0])
    assert np.isnan(matrices[0]).all() and np.array_equal(matrices[1], np.eye(3))
