"""A tiny benchmark matrix (smoke budget, two variants, two models) through the multirun and the report."""

from __future__ import annotations

import json
import re
import shutil

from test_pipeline import smoke_train_sweep

from contactbench.evaluation.report import expected_cells, write_report


def test_tiny_matrix_multirun_then_report(tmp_path):
    result = smoke_train_sweep(
        ["model=mujoco_default,sysid", "variant=frictioncubes_0,frictioncubes_1"], tmp_path / "sweep", tmp_path
    )
    assert result.returncode == 0, result.stderr[-3000:]
    documents = [json.loads(path.read_text()) for path in (tmp_path / "sweep").rglob("metrics.json")]
    values = {document["variant_values"]["friction"] for document in documents}
    assert values == {0.0, 1.0}  # numbers in metrics.json, not parsed back out of folder names
    report = write_report(tmp_path / "sweep")
    text = report.read_text()
    # 2 models x 2 variants x (val, test) rows
    assert len(re.findall(r"^\| (mujoco_default|sysid) \| frictioncubes", text, flags=re.M)) == 8
    for figure in ("frictioncubes.png", "fig7c_lowest_vertex.png"):
        assert (tmp_path / "sweep" / "figures" / figure).stat().st_size > 10_000
    # the grid: one row per variant, a column per model, test position / rotation with val position beside
    assert "| dataset | variant | mujoco_default | sysid |" in text
    cell = r"[0-9.]+ / [0-9.]+ \(val [0-9.]+\)"
    assert len(re.findall(rf"^\| frictioncubes \| friction=(0|1) \| {cell} \| {cell} \|$", text, re.M)) == 2
    for figure in ("error_over_time_frictioncubes.png", "error_over_time_frictioncubes.svg"):
        assert (tmp_path / "sweep" / "figures" / figure).stat().st_size > 10_000
    # Table 3 only over the dimension these runs vary (friction), saying what the others need
    table3 = re.findall(r"^\| (mujoco_default|sysid) \| (Yes|No) \|$", text, flags=re.M)
    assert sorted(model for model, _ in table3) == ["mujoco_default", "sysid"]
    assert "needs test runs on at least two variants of): bouncycubes (restitution)" in text
    page = (tmp_path / "sweep" / "results.html").read_text()
    assert "<table>" in page and "<style>" in page and 'src="data:image/png;base64,' in page  # one self-contained file
    # Renders: the models rebuilt from their run folders and rolled out again, drawn headless.
    final_poses = list((tmp_path / "sweep" / "renders").glob("final_poses_*.png"))
    assert final_poses and final_poses[0].stat().st_size > 10_000
    assert next((tmp_path / "sweep" / "renders").glob("rollout_*.gif")).read_bytes()[:6] == b"GIF89a"
    assert "](renders/final_poses_" in text


def test_the_report_accounts_for_every_job_the_sweep_asked_for(tmp_path):
    sweep = tmp_path / "sweep"
    result = smoke_train_sweep(["model=mujoco_default,hybrid", "variant=multicubes_2,frictioncubes_0"], sweep, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    gone = next(sweep.glob("*model=mujoco_default*variant=frictioncubes_0"))
    shutil.rmtree(gone)  # as if the sweep had stopped before this job
    cells = {(cell["model"], cell["variant"]): cell for cell in expected_cells(sweep)}
    assert cells[("mujoco_default", "multicubes_2")]["status"] == "done"
    assert cells[("hybrid", "frictioncubes_0")]["status"] == "done"
    assert cells[("mujoco_default", "frictioncubes_0")]["status"] == "missing"
    skipped = cells[("hybrid", "multicubes_2")]
    assert skipped["status"] == "skipped" and "single-body" in skipped["why"]
    text = write_report(sweep, renders=False).read_text()
    assert "4 jobs asked for: 2 done, 1 skipped, 0 failed, 0 unfinished, 1 missing." in text
