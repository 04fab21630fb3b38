"""A tiny benchmark matrix (smoke budget, two variants, two models) through the multirun and the report."""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from matplotlib.colors import to_hex
from test_pipeline import smoke_train_sweep

from contactbench.errors import ContactbenchError
from contactbench.evaluation import figures, renders
from contactbench.evaluation.collect import expected_cells
from contactbench.evaluation.figures import Run, error_over_time_figure, sweep_figure
from contactbench.evaluation.plotting import MODEL_COLOURS, model_colour, titles
from contactbench.evaluation.report import write_report


def saved_figures(monkeypatch) -> list:
    """Every figure the report saves (figures and renders), kept for a look after it was written."""
    kept = []

    def saving(figure, path):
        kept.append(figure)
        return original(figure, path)

    original = figures.save_figure
    monkeypatch.setattr(figures, "save_figure", saving)
    monkeypatch.setattr(renders, "save_figure", saving)
    return kept


def titles_outside(figure) -> list[str]:
    """The titles of a figure, as drawn, that reach past its edges (by more than a pixel)."""
    renderer = figure.canvas.get_renderer()
    figure.draw(renderer)
    edges = figure.bbox
    return [
        title.get_text()
        for title in titles(figure)
        if (box := title.get_window_extent(renderer)).x0 < edges.x0 - 1
        or box.y0 < edges.y0 - 1
        or box.x1 > edges.x1 + 1
        or box.y1 > edges.y1 + 1
    ]


def line_colours(figure) -> dict[str, str]:
    """Legend label -> colour of the lines drawn with a label, over every axes of the figure."""
    return {
        line.get_label(): to_hex(line.get_color())
        for axis in figure.axes
        for line in axis.get_lines()
        if not line.get_label().startswith("_")
    }


def test_tiny_matrix_multirun_then_report(tmp_path, monkeypatch):
    result = smoke_train_sweep(
        ["model=mujoco_default,sysid", "variant=frictioncubes_0,frictioncubes_1"], tmp_path / "sweep", tmp_path
    )
    assert result.returncode == 0, result.stderr[-3000:]
    documents = [json.loads(path.read_text()) for path in (tmp_path / "sweep").rglob("metrics.json")]
    values = {document["variant_values"]["friction"] for document in documents}
    assert values == {0.0, 1.0}  # numbers in metrics.json, not parsed back out of folder names
    drawn = saved_figures(monkeypatch)
    report = write_report(tmp_path / "sweep")
    text = report.read_text()
    # every figure and render: no title clipped, and each model in the same colour wherever it is drawn
    assert len(drawn) == 4 and not [title for figure in drawn for title in titles_outside(figure)]
    for figure in drawn:
        for label, colour in line_colours(figure).items():
            if label in ("mujoco_default", "sysid"):
                assert colour == to_hex(model_colour(label)), (label, titles(figure)[0].get_text())
    # renders as small multiples: per toss a panel for the truth and one per model, titled in the model's colour
    (poses,) = [figure for figure in drawn if titles(figure)[0].get_text().startswith("Final poses")]
    panel_titles = [axis.title.get_text() for axis in poses.axes]
    assert len(poses.axes) == 3 * 3 and sum(title.endswith("ground truth") for title in panel_titles) == 3
    sysid_panels = [axis for axis in poses.axes if axis.title.get_text().startswith("sysid: ")]
    assert len(sysid_panels) == 3 and to_hex(sysid_panels[0].title.get_color()) == to_hex(model_colour("sysid"))
    # 2 models x 2 variants x (val, test) rows
    assert len(re.findall(r"^\| (mujoco_default|sysid) \| frictioncubes", text, flags=re.M)) == 8
    for figure in ("frictioncubes.png", "fig7c_lowest_vertex.png"):
        assert (tmp_path / "sweep" / "figures" / figure).stat().st_size > 10_000
    # the grid: one row per variant, a column per model, test position / rotation with val position beside
    assert "| dataset | variant | budget | mujoco_default | sysid | not significant (95%) |" in text
    value = r"[0-9.]+ \[[0-9.]+–[0-9.]+\]"
    cell = rf"(\*\*)?{value} / {value} \(val [0-9.]+\)(\*\*| †)?"
    row = rf"^\| frictioncubes \| friction=(0|1) \| smoke \| {cell} \| {cell} \| [^|]+ \|$"
    assert len(re.findall(row, text, re.M)) == 2
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


def as_model(job: Path, folder: Path, model: str, shift: float = 0.0, own_engine: bool = False) -> None:
    """A copy of a sweep job's run as another model's: the same scores, or every toss's position error shifted; with
    own_engine, as a model simulating with the engine that made the data (runs.py marks its metrics.json so)."""
    shutil.copytree(job, folder)
    for metrics in folder.rglob("metrics.json"):
        document = json.loads(metrics.read_text())
        document.update(
            model=model, pos_err=document["pos_err"] + shift, **({"own_engine": True} if own_engine else {})
        )
        metrics.write_text(json.dumps(document))
        tosses = metrics.parent / "per_trajectory.csv"
        with open(tosses, newline="") as handle:
            rows = list(csv.DictReader(handle))
        for row in rows:
            row["pos_err"] = repr(float(row["pos_err"]) + shift)
        with open(tosses, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


def intervals_in(text: str) -> list[tuple[float, float, float]]:
    """Every 'mean [low–high]' the report prints, as numbers."""
    found = re.findall(r"([0-9.]+) \[([0-9.]+)–([0-9.]+)\]", text)
    return [(float(mean), float(low), float(high)) for mean, low, high in found]


def test_every_cell_has_its_interval_and_the_results_file_a_row_per_cell(tmp_path):
    sweep = tmp_path / "sweep"
    result = smoke_train_sweep(["model=mujoco_default", "variant=frictioncubes_0", "seed=0,1"], sweep, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    for job in sorted(sweep.glob("*model=mujoco_default*")):
        as_model(job, sweep / job.name.replace("mujoco_default", "mujoco_twin"), "mujoco_twin")
        as_model(job, sweep / job.name.replace("mujoco_default", "mujoco_worse"), "mujoco_worse", shift=1.0)
        as_model(job, sweep / job.name.replace("mujoco_default", "mujoco_own"), "mujoco_own", own_engine=True)
    text = write_report(sweep, renders=False).read_text()
    table = sweep / "results" / "smoke.csv"
    assert "results/smoke.csv" in text
    # the paper's findings judged from that file: none can be on one variant of one dataset, each says what it needs
    claims = (sweep / "results" / "smoke_claims.md").read_text()
    assert "## The paper's findings, side by side" in text and claims in text
    assert claims.count("| **not run** |") == 7 and "missing test cells: sysid" in claims
    # a row per model and split over both seeds, in a fixed order, each metric with its interval and where it is from
    with open(table, newline="") as handle:
        rows = list(csv.DictReader(handle))
    models = ("mujoco_default", "mujoco_own", "mujoco_twin", "mujoco_worse")
    assert [(row["model"], row["split"], row["seeds"]) for row in rows] == [
        (model, split, "0 1") for model in models for split in ("test", "val")
    ]
    metrics = ["pos_err", "rot_err_rad", "floor_penetration_m", "floor_penetration_true_m"]
    metrics += ["interbody_penetration_m", "pairwise_collisions"]
    assert list(rows[0]) == [
        *["model", "dataset", "variant", "paper_variant", "split", "budget", "noise_mm", "frame_stride", "seeds"],
        *["tosses", "own_engine"],
        *[f"{metric}{suffix}" for metric in metrics for suffix in ("", "_low", "_high", "_interval")],
        "pairwise_collisions_true_max",
        *["pos_err_vs_best", "rot_err_rad_vs_best"],
        *["commit", "date", "wall_s"],
    ]
    # which differences are not significant, from the file alone: the twin ties the model it copies (one of the two
    # is the best, by name where the means are equal); the model a width worse on every toss is worse
    ranked = {(row["model"], row["split"]): row["pos_err_vs_best"] for row in rows}
    for split in ("test", "val"):
        assert {ranked["mujoco_default", split], ranked["mujoco_twin", split]} == {"best", "tie"}
        assert ranked["mujoco_worse", split] == "worse"
        # a model of the engine that made the data scores as well as the best and is ranked with none
        assert ranked["mujoco_own", split] == "own engine"
    assert [row["own_engine"] for row in rows] == ["" if row["model"] != "mujoco_own" else "yes" for row in rows]
    for row in rows:
        where = ("frictioncubes", "friction=0", "yes", "smoke", "4")
        assert tuple(row[key] for key in ("dataset", "variant", "paper_variant", "budget", "tosses")) == where
        # each run recorded where it came from: this checkout's commit, when it finished, how long it took
        assert re.fullmatch(r"[0-9a-f]{40}(\+modified)?", row["commit"]), row["commit"]
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", row["date"]) and float(row["wall_s"]) > 0
        for metric in ("pos_err", "rot_err_rad", "floor_penetration_m"):
            low, mean, high = (float(row[f"{metric}{suffix}"]) for suffix in ("_low", "", "_high"))
            assert low <= mean <= high and low < high, (row["model"], metric)
            # mujoco_default scores the same at every seed: its seeds bound nothing, its tosses do
            assert row[f"{metric}_interval"] == "tosses"
    # every mean the tables print lies inside its interval (grid and every run)
    printed = intervals_in(text)
    assert len(printed) > 3 * 2 * 2 * 3 and all(low <= mean <= high for mean, low, high in printed)
    # the twin cannot be told from the model it copies; the one a width worse on every toss can, in position
    (grid_row,) = re.findall(r"^\| frictioncubes \| friction=0 \| smoke \|.*$", text, re.M)
    ties = grid_row.split(" | ")[-1]
    assert ties.startswith("pos: mujoco_default ≈ mujoco_twin; rot: ") and "mujoco_worse" not in ties.split(";")[0]
    columns = grid_row.split(" | ")
    assert " †" in columns[5]  # the twin, beside the bold best
    assert columns[4].endswith(" ‡") and "**" not in columns[4]  # the data's own engine: marked, never the best
    # same runs, same bytes
    first = {path: path.read_bytes() for path in (sweep / "results.md", table)}
    write_report(sweep, renders=False)
    assert {path: path.read_bytes() for path in first} == first
    # another sitting's groups stay as they were (a real dataset's rows here), a group scored again is replaced whole
    # (a model of this variant the run tree no longer holds goes)
    other = [{**row, "dataset": "contactnets_cube", "variant": "real", "paper_variant": ""} for row in rows]
    gone = {**rows[0], "model": "mujoco_gone"}
    with open(table, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows([gone, *rows, *other])
    write_report(sweep, renders=False)
    with open(table, newline="") as handle:
        merged = list(csv.DictReader(handle))
    assert merged == other + rows  # in cell order: contactnets_cube before frictioncubes
    table.write_text("model,dataset\nsysid,x\n")
    with pytest.raises(ContactbenchError, match=r"smoke\.csv: field 'variant' missing"):
        write_report(sweep, renders=False)


def toss_run(model: str, running: list[int], pos_err: list[float]) -> Run:
    """A test run of 8 tosses whose per-frame error curve is pos_err, with running[t] tosses still scored at t."""
    per_frame = {"pos_err": pos_err, "rot_err_rad": pos_err, "n_trajectories": running}
    summary = {
        "model": model,
        "dataset": "contactnets_cube",
        "variant": "recorded",
        "split": "test",
        "seed": 0,
        "n_trajectories": 8,
        "pos_err": float(np.mean(pos_err)),
        "per_frame": per_frame,
    }
    return Run(summary, {"pos_err": np.array(pos_err)})


def test_error_over_time_greys_out_frames_with_under_a_quarter_of_the_tosses(tmp_path, monkeypatch):
    drawn = saved_figures(monkeypatch)
    running = [8, 8, 8, 6, 4, 1, 1, 1]  # frames 5-7: fewer than a quarter of 8 tosses
    error = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 9.0, 0.1]  # the swing at the end is a mean over one toss
    runs = [toss_run("sysid", running, error), toss_run("my_own_model", running, error[::-1])]
    assert error_over_time_figure(runs, "contactnets_cube", tmp_path / "error.png").stat().st_size > 10_000
    (figure,) = drawn
    position = figure.axes[0]
    coloured = [line for line in position.get_lines() if line.get_label() == "sysid"]
    grey = [line for line in position.get_lines() if to_hex(line.get_color()) == to_hex("0.6")]
    assert np.isfinite(coloured[0].get_ydata()).nonzero()[0].tolist() == [0, 1, 2, 3, 4]
    assert np.isfinite(grey[0].get_ydata()).nonzero()[0].tolist() == [4, 5, 6, 7]  # from the last drawn on
    assert "< 25% of tosses running" in [text.get_text() for text in position.get_legend().get_texts()]
    assert "grey where fewer than 25%" in figure._suptitle.get_text().replace("\n", " ")
    assert not titles_outside(figure)  # the long title is wrapped, not cut off
    # a model of one's own gets one colour that is nobody else's, the same in every figure
    assert to_hex(coloured[0].get_color()) == to_hex(model_colour("sysid"))
    assert model_colour("my_own_model") == model_colour("my_own_model") not in MODEL_COLOURS.values()


def test_sweep_figure_titles_fit_and_models_keep_their_colours(tmp_path, monkeypatch):
    drawn = saved_figures(monkeypatch)
    runs = [
        Run(
            {
                "model": model,
                "dataset": "frictioncubes",
                "variant": f"friction={mu}",
                "variant_values": {"friction": mu},
                "pos_err": 0.1 + mu,
                "rot_err_rad": 0.2,
                "floor_penetration_m": 1e-3,
                "seed": 0,
            },
            {"pos_err": np.full(4, 0.1 + mu), "rot_err_rad": np.full(4, 0.2), "floor_penetration_m": np.full(4, 1e-3)},
        )
        for model in ("hybrid", "gnn")
        for mu in (0.0, 0.5, 1.0)
    ]
    sweep_figure(runs, "frictioncubes", tmp_path / "sweep.png")
    (figure,) = drawn
    assert not titles_outside(figure)
    assert line_colours(figure) == {"hybrid": to_hex("tab:brown"), "gnn": to_hex("tab:red")}


def test_a_run_folders_provenance_that_is_not_an_object_is_one_error_naming_the_file(tmp_path):
    from contactbench import provenance
    from contactbench.errors import ContactbenchError

    assert provenance.read(tmp_path) == {}  # an older run wrote none: the results file says 'unknown'
    for text in ("{", "[1, 2]", "\xff"):
        (tmp_path / "provenance.json").write_text(text, encoding="latin-1")
        with pytest.raises(ContactbenchError, match="provenance.json: ") as raised:
            provenance.read(tmp_path)
        assert "\n" not in str(raised.value)


def _results_row(model: str, dataset: str, pos: float, rank: str, **extra) -> dict:
    from contactbench.evaluation.results_file import HEADER

    row = dict.fromkeys(HEADER, "")
    row.update(model=model, dataset=dataset, variant="real", split="test", budget="quick", noise_mm="0", seeds="0")
    row.update(pos_err=pos, pos_err_low=pos - 0.01, pos_err_high=pos + 0.01, pos_err_vs_best=rank)
    row.update(rot_err_rad=0.5, rot_err_rad_low=0.4, rot_err_rad_high=0.6, rot_err_rad_vs_best="tie")
    row.update(commit="a" * 40, date="2026-11-27T17:00:00Z", wall_s="120.0", **extra)
    return row


def test_the_readme_headline_is_written_from_the_results_file_alone(tmp_path):
    from contactbench.evaluation import headline
    from contactbench.evaluation.results_file import HEADER

    rows = [
        _results_row("sysid", "contactnets_cube", 0.26, "worse"),
        _results_row("sysid_drake", "contactnets_cube", 0.145, "best"),
        _results_row("gnn", "contactnets_cube", 0.15, "tie"),
        _results_row("gnn", "contactnets_elbow", 0.70, "best"),
        _results_row("gnn", "frictioncubes", 0.01, "best"),  # a synthetic variant: not in the headline
    ]
    results, readme = tmp_path / "quick.csv", tmp_path / "README.md"
    with open(results, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=HEADER, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    readme.write_text(f"# title\n\n{headline.BEGIN}\nwritten by hand\n{headline.END}\n\nthe rest\n")
    args = ["--results", str(results), "--readme", str(readme)]
    assert headline.main([*args, "--check"]) == 1  # a hand-written table is not the file's
    assert headline.main(args) == 0 and headline.main([*args, "--check"]) == 0
    text = readme.read_text()
    assert text.startswith("# title\n\n") and text.endswith("\n\nthe rest\n") and "written by hand" not in text
    lines = [line for line in text.splitlines() if line.startswith("| `")]
    # the fixed model order, the best bold, a tie marked, a missing run a dash, intervals beside every mean
    assert [line.split("`")[1] for line in lines] == ["sysid", "sysid_drake", "gnn"]
    assert lines[1].startswith("| `sysid_drake` | **0.145** [0.135–0.155] | 0.50 ≈ [0.40–0.60] | – | – |")
    assert "0.150 ≈ [0.140–0.160]" in lines[2] and "**0.700** [0.690–0.710]" in lines[2]
    assert "0.010" not in text and "commit aaaaaaaaaaaa" in text and "2026-11-27" in text
    # a results file without the ranking columns is one line naming it
    with open(results, "w", newline="") as handle:
        handle.write("model,dataset\nsysid,contactnets_cube\n")
    assert headline.main(args) == 2 and readme.read_text() == text
