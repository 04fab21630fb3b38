"""The real pipeline, composed with Hydra's compose API as the entry points compose it, on budget=smoke."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from contactbench import runs
from contactbench.config import CONFIG_DIR, REPO_ROOT
from contactbench.errors import ContactbenchError

REQUIRED_KEYS = {
    "model",
    "dataset",
    "variant",
    "split",
    "n_trajectories",
    "context_frames",
    "pos_err",
    "rot_err_rad",
    "floor_penetration_m",
    "interbody_penetration_m",
    "pairwise_collisions",
}


def compose_config(name: str, overrides: list[str], tmp_path: Path):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(
            config_name=name,
            overrides=[f"paths.log_dir={tmp_path}/outputs", f"paths.data_dir={tmp_path}/data", *overrides],
        )


def run_entry_point(script: str, overrides: list[str], tmp_path: Path, timeout: float = 300, **kwargs):
    command = [
        sys.executable,
        str(REPO_ROOT / script),
        *overrides,
        f"paths.log_dir={tmp_path}/outputs",
        f"paths.data_dir={tmp_path}/data",
    ]
    environment = {**os.environ, "WANDB_MODE": "disabled"}
    return subprocess.run(
        command, capture_output=True, text=True, timeout=timeout, env=environment, cwd=tmp_path, **kwargs
    )


def smoke_train_sweep(overrides: list[str], sweep_dir: Path, tmp_path: Path, timeout: float = 400):
    """`train.py -m` over the overrides at budget=smoke, on freshly generated 6/4/4-toss splits, scored on test."""
    return run_entry_point(
        "train.py",
        [
            "-m",
            *overrides,
            "budget=smoke",
            "test=true",
            "generation.split_sizes={train:6,val:4,test:4}",
            f"hydra.sweep.dir={sweep_dir}",
        ],
        tmp_path,
        timeout=timeout,
    )


def test_evaluate_analytical_baselines_on_real_cube(tmp_path):
    for overrides in (["model=mujoco_default"], ["model=mujoco_fixed", "model.preset=acosta2022"]):
        cfg = compose_config("evaluate", ["dataset=contactnets_cube", *overrides], tmp_path)
        document = runs.evaluate(cfg, tmp_path / cfg.model.name)
        assert REQUIRED_KEYS <= set(document)
        assert document["n_trajectories"] == 110 and document["split"] == "test"
        assert document["interbody_penetration_m"] is None and document["pairwise_collisions"] is None
        assert 0 < document["pos_err"] < 5 and 0 < document["rot_err_rad"] < 3.2
        written = json.loads((tmp_path / cfg.model.name / "metrics.json").read_text())
        assert written["pos_err"] == document["pos_err"]
        assert len(written["per_frame"]["pos_err"]) == 133
        assert (tmp_path / cfg.model.name / "per_trajectory.csv").read_text().count("\n") == 111
    # The published parameters were identified on this cube: they must beat MuJoCo's untuned defaults.
    default = json.loads((tmp_path / "mujoco_default" / "metrics.json").read_text())
    fixed = json.loads((tmp_path / "mujoco_fixed_acosta2022" / "metrics.json").read_text())
    assert fixed["pos_err"] < default["pos_err"]


def test_train_never_loads_test_unless_asked(tmp_path, monkeypatch):
    loaded = []
    original = runs.read_recordings
    monkeypatch.setattr(
        runs, "read_recordings", lambda path, splits: loaded.append(list(splits)) or original(path, splits)
    )
    cfg = compose_config("train", ["dataset=contactnets_cube", "model=mujoco_default"], tmp_path)
    runs.train(cfg, tmp_path / "run")
    assert loaded == [["train", "val"]]
    assert (tmp_path / "run" / "val" / "metrics.json").is_file() and not (tmp_path / "run" / "test").exists()


def test_sysid_smoke_fits_saves_parameters_and_evaluate_scores_them(tmp_path):
    cfg = compose_config("train", ["dataset=contactnets_cube", "model=sysid", "budget=smoke"], tmp_path)
    run_dir = tmp_path / "train-run"
    val_pos_err = runs.train(cfg, run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    assert set(fitted["parameters"]) == {"object_friction_0", "floor_friction", "floor_stiffness", "floor_damping"}
    assert 0 <= fitted["parameters"]["floor_friction"] <= 1 and 1e2 <= fitted["parameters"]["floor_stiffness"] <= 1e4
    assert val_pos_err == json.loads((run_dir / "val" / "metrics.json").read_text())["pos_err"]
    checkpoint = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)
    assert torch.isfinite(checkpoint["state_dict"]["selected"]).all()
    eval_cfg = compose_config(
        "evaluate",
        ["dataset=contactnets_cube", "model=sysid", "budget=smoke", f"train_dir={run_dir}", "split=val"],
        tmp_path,
    )
    document = runs.evaluate(eval_cfg, tmp_path / "eval-run")
    assert document["model"] == "sysid" and document["pos_err"] == pytest.approx(val_pos_err)


def test_a_setting_chosen_on_val_is_the_best_candidate_and_evaluate_scores_it(tmp_path):
    """choose_on_val fits every setting from the same start and keeps the lowest best val/pos_err; evaluate.py
    restores that candidate's checkpoint."""
    overrides = [
        "dataset=contactnets_cube",
        "model=gnn",
        "budget=smoke",
        "~model.choose_on_val",
        "+model.choose_on_val.module.lr=[1e-3,1e-2]",
    ]
    run_dir = tmp_path / "train-run"
    val_pos_err = runs.train(compose_config("train", overrides, tmp_path), run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    scores = {entry["setting"]["module.lr"]: entry["val_pos_err"] for entry in fitted["candidates"]}
    assert set(scores) == {1e-3, 1e-2} and fitted["chosen_on_val"]["module.lr"] == min(scores, key=scores.get)
    assert fitted["checkpoint"].startswith(f"lr={fitted['chosen_on_val']['module.lr']:g}/")
    assert sorted(path.name for path in (run_dir / "checkpoints").iterdir()) == ["lr=0.001", "lr=0.01"]
    header = (run_dir / "csv" / "metrics.csv").read_text().splitlines()[0]
    assert "lr=0.001/val/pos_err" in header and "lr=0.01/val/pos_err" in header
    document = runs.evaluate(
        compose_config("evaluate", [*overrides, f"train_dir={run_dir}", "split=val"], tmp_path), tmp_path / "eval"
    )
    assert document["pos_err"] == pytest.approx(val_pos_err)


def test_a_setting_chosen_early_goes_on_alone_ends_as_its_fit_alone_and_a_resumed_run_keeps_the_choice(tmp_path):
    """choose_at_step: every setting trains to that step, the one best on val so far goes on to max_steps (resumed
    from its checkpoint there, it ends bit for bit as its uninterrupted fit: the weight average keeps the buffers in
    step), the others keep their score at that step; a run resumed after the choice keeps it."""
    grid = ["dataset=contactnets_cube", "model=gnn", "budget=smoke", "~model.choose_on_val"]
    steps = ["model.budgets.smoke.max_steps=20", "model.budgets.smoke.val_check_interval=10"]
    overrides = [*grid, *steps, "+model.choose_on_val.module.lr=[1e-3,3e-2]", "model.budgets.smoke.choose_at_step=10"]
    run_dir = tmp_path / "train-run"
    runs.train(compose_config("train", overrides, tmp_path), run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    winner = f"lr={fitted['chosen_on_val']['module.lr']:g}"
    (loser,) = {"lr=0.001", "lr=0.03"} - {winner}

    def step(name: str, checkpoint: str = "last") -> int:
        return torch.load(run_dir / "checkpoints" / name / f"{checkpoint}.ckpt", weights_only=True)["global_step"]

    assert fitted["chosen_at_step"] == 10 and (step(winner), step(loser)) == (20, 10)
    record = json.loads((run_dir / "checkpoints" / "chosen_at_step.json").read_text())
    at_ten = {f"lr={entry['setting']['module.lr']:g}": entry["val_pos_err"] for entry in record["candidates"]}
    assert at_ten[winner] <= at_ten[loser]
    assert {f"lr={e['setting']['module.lr']:g}": e["val_pos_err"] for e in fitted["candidates"]}[loser] == at_ten[loser]
    # the winner, paused at step 10 and resumed, ends with the very weights of its fit alone, uninterrupted
    alone_dir = tmp_path / "alone"
    lr = fitted["chosen_on_val"]["module.lr"]
    runs.train(compose_config("train", [*grid, *steps, f"+model.choose_on_val.module.lr=[{lr}]"], tmp_path), alone_dir)
    for checkpoint in ("best", "last"):
        resumed, alone = (
            torch.load(folder / "checkpoints" / winner / f"{checkpoint}.ckpt", weights_only=True)
            for folder in (run_dir, alone_dir)
        )
        for part in ("state_dict", "current_model_state"):
            for name, value in alone[part].items():
                torch.testing.assert_close(
                    resumed[part][name], value, atol=0, rtol=0, msg=f"{checkpoint} {part} {name}"
                )
    # resumed after the choice: the record holds it (the winner's own best is now past step 10), nothing trains again
    (run_dir / "fitted.json").unlink()
    runs.train(compose_config("train", [*overrides, "resume=true"], tmp_path), run_dir)
    assert json.loads((run_dir / "fitted.json").read_text())["candidates"] == fitted["candidates"]
    assert (step(winner), step(loser)) == (20, 10)
    record["candidates"][0]["checkpoint"] = "../../elsewhere.ckpt"
    (run_dir / "checkpoints" / "chosen_at_step.json").write_text(json.dumps(record))
    with pytest.raises(ContactbenchError, match=r"chosen_at_step\.json: field 'checkpoint' must be lr="):
        runs.train(compose_config("train", [*overrides, "resume=true"], tmp_path), run_dir)


def test_last_checkpoint_is_the_last_validation_not_the_best(tmp_path):
    """A killed run resumes from last.ckpt: written at every validation, not only when the monitored score improves
    (here the monitor, train/seconds, is lowest at the first validation)."""
    overrides = [
        "dataset=contactnets_cube",
        "model=gnn",
        "budget=smoke",
        "~model.choose_on_val",
        "model.budgets.smoke.max_steps=30",
        "model.budgets.smoke.val_check_interval=10",
        "model.callbacks.checkpoint.monitor=train/seconds",
    ]
    run_dir = tmp_path / "train-run"
    runs.train(compose_config("train", overrides, tmp_path), run_dir)
    step = {
        name: torch.load(run_dir / "checkpoints" / f"{name}.ckpt", weights_only=True)["global_step"]
        for name in ("best", "last")
    }
    assert step == {"best": 10, "last": 30}
    assert json.loads((run_dir / "fitted.json").read_text())["checkpoint"] == "best.ckpt"


def test_sysid_process_exits_by_itself(tmp_path):
    """nevergrad's recast optimisers leave threads behind; train.py must still exit on its own."""
    result = run_entry_point(
        "train.py", ["model=sysid", "dataset=contactnets_cube", "budget=smoke"], tmp_path, timeout=240
    )
    assert result.returncode == 0, result.stderr[-2000:]


def test_sysid_killed_run_resumes_instead_of_starting_over(tmp_path):
    overrides = [
        "model=sysid",
        "dataset=contactnets_cube",
        "budget=smoke",
        "model.module.evaluations=96",
        "model.module.num_workers=4",
        "model.module.restarts=1",
    ]
    command = [
        sys.executable,
        str(REPO_ROOT / "train.py"),
        f"paths.log_dir={tmp_path}/outputs",
        f"paths.data_dir={tmp_path}/data",
        *overrides,
    ]
    environment = {**os.environ, "WANDB_MODE": "disabled"}
    process = subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=environment, cwd=tmp_path
    )
    checkpoint = (
        tmp_path
        / "outputs"
        / "train"
        / "sysid"
        / "contactnets_cube"
        / "real"
        / "budget=smoke,seed=0"
        / "checkpoints"
        / "last.ckpt"
    )
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and process.poll() is None:
        if (
            checkpoint.exists()
            and torch.load(checkpoint, weights_only=True)["callbacks"]["NevergradSearch"]["generation"] >= 3
        ):
            break
        time.sleep(0.05)
    assert process.poll() is None, "the search finished before it could be killed; give it more evaluations"
    process.send_signal(signal.SIGKILL)
    process.wait()
    done_before = torch.load(checkpoint, weights_only=True)["callbacks"]["NevergradSearch"]["evaluations"]
    assert 0 < done_before < 96
    result = subprocess.run(command, capture_output=True, text=True, timeout=240, env=environment, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    log_text = (checkpoint.parents[1] / "train.log").read_text()
    assert f"{done_before} evaluations done so far" in log_text
    assert torch.load(checkpoint, weights_only=True)["callbacks"]["NevergradSearch"]["evaluations"] == 96


def test_bad_dataset_path_is_one_clear_error(tmp_path):
    result = run_entry_point(
        "evaluate.py", ["dataset=recordings", f"recordings={tmp_path}/nowhere"], tmp_path, timeout=120
    )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"error: {tmp_path}/nowhere: not a dataset folder (expected a folder with meta.json)"
    ]
    assert "Traceback" not in result.stdout + result.stderr


def test_multirun_names_job_folders_after_their_overrides(tmp_path):
    result = run_entry_point(
        "evaluate.py",
        [
            "-m",
            "model=mujoco_default,mujoco_fixed",
            "variant=contactnets_cube",
            "split=val",
            f"hydra.sweep.dir={tmp_path}/sweep",
        ],
        tmp_path,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    for model, name in (("mujoco_default", "mujoco_default"), ("mujoco_fixed", "mujoco_fixed_acosta2022")):
        document = json.loads(
            (tmp_path / "sweep" / f"model={model},split=val,variant=contactnets_cube" / "metrics.json").read_text()
        )
        assert document["model"] == name and document["n_trajectories"] == 165


def test_a_run_folder_refuses_to_resume_or_serve_other_settings(tmp_path):
    run_dir = tmp_path / "train-run"
    runs.train(compose_config("train", ["dataset=contactnets_cube", "model=sysid", "budget=smoke"], tmp_path), run_dir)
    changed = ["dataset=contactnets_cube", "model=sysid", "budget=smoke", "model.module.position_exponent=1"]
    with pytest.raises(ContactbenchError, match="other settings.*resume=false"):
        runs.train(compose_config("train", changed, tmp_path), run_dir)
    with pytest.raises(ContactbenchError, match="cannot score the model of"):
        runs.evaluate(
            compose_config("evaluate", [*changed, f"train_dir={run_dir}", "split=val"], tmp_path), tmp_path / "eval"
        )


def test_evaluate_refuses_to_rewrite_scores_of_settings_its_folder_name_does_not_say(tmp_path):
    """context_frames and a model field are not in evaluate's folder name: scores of other ones there are kept, and
    the refusal is one line naming the setting and what to do."""
    from conftest import falling_cubes

    from contactbench.recordings import write_recordings

    write_recordings(tmp_path / "mine", falling_cubes(n_trajectories=3, n_frames=12))
    command = ["model=mujoco_default", "dataset=recordings", f"recordings={tmp_path / 'mine'}"]
    assert run_entry_point("evaluate.py", command, tmp_path).returncode == 0
    (metrics,) = (tmp_path / "outputs" / "evaluate").rglob("metrics.json")
    scores = metrics.read_bytes()
    for changed, named in (
        ("context_frames=4", "context_frames: 6 there, 4 here"),
        ("model.contact_model.substeps=2", "model.contact_model.substeps: 1 there, 2 here"),
    ):
        refused = run_entry_point("evaluate.py", [*command, changed], tmp_path)
        message = refused.stderr.strip()
        assert refused.returncode == 2 and len(message.splitlines()) == 1, message
        assert named in message and "hydra.run.dir=FOLDER" in message and "overwrite=true" in message, message
        assert metrics.read_bytes() == scores
    replaced = run_entry_point("evaluate.py", [*command, "context_frames=4", "overwrite=true"], tmp_path)
    assert replaced.returncode == 0, replaced.stderr[-2000:]
    assert json.loads(metrics.read_text())["context_frames"] == 4
    assert run_entry_point("evaluate.py", [*command, "context_frames=4"], tmp_path).returncode == 0  # as recorded


def test_models_never_see_the_test_split_or_the_generator(tmp_path, monkeypatch):
    seen = []
    from contactbench.models.analytical import MujocoContactModel

    original_fit, original_rollout = MujocoContactModel.fit, MujocoContactModel.rollout
    monkeypatch.setattr(
        MujocoContactModel,
        "fit",
        lambda self, dataset: (
            seen.append(("fit", sorted(dataset.splits), "generator" in dataset.meta)) or original_fit(self, dataset)
        ),
    )
    monkeypatch.setattr(
        MujocoContactModel,
        "rollout",
        lambda self, scene, context: (
            seen.append(("rollout", type(scene).__name__, "generator" in scene.meta))
            or original_rollout(self, scene, context)
        ),
    )
    runs.train(
        compose_config("train", ["dataset=contactnets_cube", "model=mujoco_default", "test=true"], tmp_path),
        tmp_path / "run",
    )
    # rollouts get the scene alone: no trajectories to read
    assert seen == [("fit", ["train", "val"], False), ("rollout", "Scene", False), ("rollout", "Scene", False)]
