"""Bring your own model (docs/ADDING_A_MODEL.md): a model living outside contactbench, one Python file and one YAML,
runs through train.py, evaluate.py and the report, and is scored the same when rebuilt from its run folder."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import falling_cubes
from test_pipeline import compose_config, run_entry_point

from contactbench import restore, runs
from contactbench.config import REPO_ROOT
from contactbench.errors import ContactbenchError
from contactbench.recordings import write_recordings

EXTERNAL = Path(__file__).parent / "external_model"


def test_a_model_outside_the_package_trains_evaluates_and_reports_as_fitted(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(EXTERNAL))
    searchpath = f"hydra.searchpath=[file://{EXTERNAL / 'conf'}]"
    sweep = tmp_path / "sweep"
    model = ["model=ballistic", "dataset=contactnets_cube", "budget=smoke", searchpath]
    trained = run_entry_point("train.py", ["-m", *model, "test=true", f"hydra.sweep.dir={sweep}"], tmp_path)
    assert trained.returncode == 0, trained.stderr[-2000:]
    (run,) = [path for path in sweep.iterdir() if path.is_dir()]
    fitted = json.loads((run / "fitted.json").read_text())
    assert fitted["model"] == "ballistic" and fitted["state"]["stop_frame"] > 6
    at_train = json.loads((run / "test" / "metrics.json").read_text())
    evaluated = run_entry_point(
        "evaluate.py", [*model, "split=test", f"train_dir='{run}'", f"hydra.run.dir={tmp_path / 'eval'}"], tmp_path
    )
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]
    at_evaluate = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert at_evaluate["pos_err"] == at_train["pos_err"] and at_evaluate["rot_err_rad"] == at_train["rot_err_rad"]
    # without train_dir: the run index (paths.log_dir/index) finds the model the sweep fitted
    found = run_entry_point("evaluate.py", [*model, "split=test", f"hydra.run.dir={tmp_path / 'eval3'}"], tmp_path)
    assert found.returncode == 0, found.stderr[-2000:]
    assert json.loads((tmp_path / "eval3" / "metrics.json").read_text())["pos_err"] == at_train["pos_err"]
    report = [sys.executable, "-m", "contactbench.evaluation.report", str(sweep)]
    reported = subprocess.run(report, capture_output=True, text=True, timeout=300)
    assert reported.returncode == 0, reported.stderr[-2000:]
    assert "ballistic" in (sweep / "results.md").read_text()
    # A fitted state is JSON data, checked before the model sees it: anything else is one line naming file and field.
    for bad in ('{"model": "ballistic", "state": {"stop_frame": NaN}}', '{"model": "ballistic"}', "not json"):
        (run / "fitted.json").write_text(bad)
        refused = run_entry_point(
            "evaluate.py", [*model, "split=test", f"train_dir='{run}'", f"hydra.run.dir={tmp_path / 'eval2'}"], tmp_path
        )
        message = refused.stderr.strip()
        assert refused.returncode == 2 and len(message.splitlines()) == 1, message
        assert str(run / "fitted.json") in message and (("'state'" in message) or "not valid JSON" in message)
        assert (run / "fitted.json").read_text() == bad
    (entry,) = (tmp_path / "outputs" / "index").iterdir()
    entry.write_text("{not json")
    refused = run_entry_point("evaluate.py", [*model, "split=test", f"hydra.run.dir={tmp_path / 'eval4'}"], tmp_path)
    assert refused.returncode == 2 and str(entry) in refused.stderr and len(refused.stderr.strip().splitlines()) == 1


DOC = REPO_ROOT / "docs" / "ADDING_A_MODEL.md"
PLACEHOLDER = "/path/to/your_project"


def documented_files(text: str) -> dict[str, str]:
    """The guide's code blocks that open with a comment naming their file (`# my_models/my_model.py`)."""
    blocks = re.findall(r"^```(?:python|yaml)\n# ([\w./-]+)\n(.*?)^```", text, re.S | re.M)
    return {name: f"# {name}\n{body}" for name, body in blocks}


def documented_commands(text: str) -> list[list[str]]:
    """The guide's shell lines, continuation lines joined, as words."""
    blocks = re.findall(r"^```bash\n(.*?)^```", text, re.S | re.M)
    lines = "\n".join(blocks).replace("\\\n", " ").splitlines()
    return [shlex.split(line, comments=True) for line in lines if shlex.split(line, comments=True)]


def test_the_guide_s_model_runs_as_written(tmp_path):
    """docs/ADDING_A_MODEL.md's files, written where it says, trained by its own command (budget=smoke)."""
    text = DOC.read_text()
    project = tmp_path / "your_project"
    files = documented_files(text)
    assert {Path(name).suffix for name in files} == {".py", ".yaml"}, sorted(files)
    for name, body in files.items():
        (project / name).parent.mkdir(parents=True, exist_ok=True)
        (project / name).write_text(body)
    commands = documented_commands(text)
    (export,) = [words for words in commands if words[0] == "export"]
    assert export[1].startswith("PYTHONPATH=")
    python_path = export[1].split("=", 1)[1].replace(PLACEHOLDER, str(project))
    train = next(words for words in commands if words[:2] == ["python", "train.py"])
    overrides = [word.replace(PLACEHOLDER, str(project)).replace("budget=quick", "budget=smoke") for word in train[2:]]
    run = tmp_path / "run"
    trained = run_train([*overrides, f"hydra.run.dir={run}"], tmp_path, python_path)
    assert trained.returncode == 0, trained.stderr[-3000:]
    fitted = json.loads((run / "fitted.json").read_text())
    assert fitted["model"] == "my_model" and fitted["state"], fitted
    assert (run / "test" / "metrics.json").is_file()
    # Without PYTHONPATH the model's module cannot be imported: one line that says so and what to do.
    again = run_train([*overrides, f"hydra.run.dir={tmp_path / 'run2'}"], tmp_path, None)
    message = again.stderr.strip()
    assert again.returncode == 2 and len(message.splitlines()) == 1, message
    assert "my_models.my_model.MyModel" in message and "PYTHONPATH" in message, message


def run_train(overrides: list[str], tmp_path: Path, python_path: str | None) -> subprocess.CompletedProcess:
    """train.py in a fresh shell's environment: PYTHONPATH only as the guide sets it."""
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    env.update({"WANDB_MODE": "disabled", **({"PYTHONPATH": python_path} if python_path else {})})
    command = [sys.executable, str(REPO_ROOT / "train.py"), *overrides, f"paths.log_dir={tmp_path}/outputs"]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)


def test_a_target_that_is_not_a_model_is_one_line_naming_the_contract(tmp_path):
    """What a model's YAML builds is checked against models/base.py before anything is fitted, scored or loaded."""
    write_recordings(tmp_path / "ds", falling_cubes(n_trajectories=2, n_frames=8))
    data = ["dataset=recordings", f"recordings={tmp_path / 'ds'}"]
    cfg = compose_config("evaluate", [*data, "model.contact_model._target_=collections.OrderedDict"], tmp_path)
    with pytest.raises(ContactbenchError, match=r"^model.contact_model._target_ is collections.OrderedDict, not a "):
        runs.evaluate(cfg, tmp_path / "eval")
    cfg = compose_config("evaluate", [*data, "model=gnn", "model.module._target_=torch.nn.Linear"], tmp_path)
    with pytest.raises(ContactbenchError, match=r"subclass of contactbench.models.base.ContactModule"):
        restore.load_module(cfg, None, tmp_path / "no.ckpt")
