"""Every logger back-end records a run's config and scores, offline, without asking for anything."""

from __future__ import annotations

import sqlite3

import pytest
from conftest import falling_cubes
from test_pipeline import compose_config

from contactbench import runs
from contactbench.recordings import write_recordings


@pytest.fixture
def recorded_dataset(tmp_path):
    return write_recordings(tmp_path / "falling", falling_cubes(n_trajectories=3, n_frames=20, n_bodies=2))


@pytest.mark.parametrize("logger", ["csv", "tensorboard", "mlflow", "wandb"])
def test_logger_records_scores(tmp_path, recorded_dataset, logger, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path))
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    cfg = compose_config(
        "evaluate", ["dataset=recordings", f"recordings={recorded_dataset}", f"logger={logger}", "split=val"], tmp_path
    )
    document = runs.evaluate(cfg, tmp_path / "run")
    assert document["dataset"] == "recordings" and document["variant"].startswith("falling-")
    assert document["interbody_penetration_m"] is not None and document["pairwise_collisions"] is not None
    if logger == "csv":
        text = (tmp_path / "run" / "csv" / "metrics.csv").read_text()
        assert "val/pos_err" in text
    elif logger == "tensorboard":
        assert list((tmp_path / "run" / "tensorboard").glob("events.out.tfevents.*"))
    elif logger == "mlflow":
        with sqlite3.connect(tmp_path / "outputs" / "mlflow.db") as connection:
            keys = {row[0] for row in connection.execute("select key from metrics")}
        assert "val/pos_err" in keys
    else:
        assert cfg.logger.offline is True
        assert list(tmp_path.rglob("offline-run-*"))


def test_mlflow_holds_curated_params_tags_curves_and_artifacts(tmp_path, recorded_dataset):
    from mlflow.tracking import MlflowClient

    overrides = ["dataset=recordings", f"recordings={recorded_dataset}", "logger=mlflow", "model=sysid", "budget=smoke"]
    runs.train(compose_config("train", overrides, tmp_path), tmp_path / "run")
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/outputs/mlflow.db")
    (run,) = client.search_runs(client.get_experiment_by_name("contactbench").experiment_id)
    params = run.data.params
    assert params["model.name"] == "sysid" and params["budget.name"] == "smoke" and params["budget.evaluations"] == "16"
    assert params["dataset.variant"].startswith("falling-") and params["observation.noise_mm"] == "0.0"
    assert not [key for key in params if key.startswith(("budget.gnn", "budget.hybrid", "hydra", "paths"))]
    assert len(params) < 40
    tags = run.data.tags
    assert tags["run"] == f"sysid/recordings/{params['dataset.variant']}/smoke" and tags["task"] == "train"
    assert tags["val/n_trajectories"] == "3" and "val/rollout_seconds" in tags
    metrics = run.data.metrics
    assert "val/pos_err" in metrics and "val/n_trajectories" not in metrics and "hp_metric" not in metrics
    curve = client.get_metric_history(run.info.run_id, "val/pos_err_by_frame")
    assert sorted(point.step for point in curve) == list(range(6, 20))  # the frames after the context
    artifacts = {item.path for folder in ("", "val", "run") for item in client.list_artifacts(run.info.run_id, folder)}
    assert {"val/metrics.json", "val/per_trajectory.csv", "run/scene.xml"} <= artifacts
