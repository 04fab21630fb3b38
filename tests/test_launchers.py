"""Scale-out: the cluster launcher config composes to Slurm, and the same sweep runs through submitit locally."""

from __future__ import annotations

import json
from pathlib import Path

from hydra import compose, initialize_config_dir
from test_pipeline import smoke_train_sweep

from contactbench.config import CONFIG_DIR


def test_cluster_and_local_launcher_configs_compose():
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cluster = compose("train", overrides=["hydra/launcher=cluster"], return_hydra_config=True).hydra.launcher
        local = compose("train", overrides=["hydra/launcher=local"], return_hydra_config=True).hydra.launcher
    assert cluster._target_.endswith("SlurmLauncher") and cluster.gpus_per_node == 1 and cluster.cpus_per_task == 8
    assert local._target_.endswith("JoblibLauncher") and local.n_jobs == 2


def test_a_sweep_runs_through_submitit_local(tmp_path):
    result = smoke_train_sweep(
        ["hydra/launcher=submitit_local", "model=mujoco_default", "variant=frictioncubes_0,frictioncubes_1"],
        tmp_path / "sweep",
        tmp_path,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = sorted((tmp_path / "sweep").rglob("test/metrics.json"))
    assert len(metrics) == 2
    assert list((tmp_path / "sweep" / ".submitit").iterdir())  # submitit ran the jobs, not Hydra's basic launcher


def test_stepped_engines_run_inside_the_local_launchers_workers(tmp_path):
    # joblib's workers set multiprocessing's default start method to loky's; the stepped engines' worker processes
    # (and the generator's) must still start there, or every toss of a PyBullet or Drake row is NaN and skipped.
    result = smoke_train_sweep(
        ["hydra/launcher=local", "model=bullet_default,drake_default", "variant=frictioncubes_0"],
        tmp_path / "sweep",
        tmp_path,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = sorted((tmp_path / "sweep").rglob("test/metrics.json"))
    assert len(metrics) == 2, result.stderr[-3000:]
    # PyBullet made these tosses: its own engine's row says so, Drake's does not (the report ranks it with none)
    own = {document["model"]: document.get("own_engine") for document in map(json.loads, map(Path.read_text, metrics))}
    assert own == {"bullet_default": True, "drake_default": None}
