"""Bring your own model (docs/ADDING_A_MODEL.md): a model living outside contactbench, one Python file and one YAML,
runs through train.py, evaluate.py and the report, and is scored the same when rebuilt from its run folder."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from test_pipeline import run_entry_point

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
