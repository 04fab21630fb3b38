"""A newcomer's first hour (issue 48): no run overwrites or blocks another, and the report says what it mixes."""

from __future__ import annotations

import csv
import json
import logging
import re
from pathlib import Path

import pytest
from conftest import falling_cubes
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from contactbench import runs
from contactbench.config import CONFIG_DIR
from contactbench.errors import ContactbenchError
from contactbench.evaluation.report import write_report
from contactbench.recordings import write_recordings

SMALL = "generation.split_sizes={train:6,val:4,test:4}"


class TakesNoArguments:
    """A model of one's own whose YAML passes arguments its class does not take: TypeError in the constructor."""


def composed(name: str, overrides: list[str], tmp_path: Path):
    """The config an entry point gets, and the run folder Hydra would give it (conf/hydra/default.yaml's run.dir)."""
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(
            config_name=name,
            overrides=[f"paths.log_dir={tmp_path}/outputs", f"paths.data_dir={tmp_path}/data", *overrides],
            return_hydra_config=True,
        )
    run_dir = Path(cfg.hydra.run.dir)
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg, run_dir


def two_cubes_named_alike(tmp_path: Path) -> tuple[Path, Path]:
    """~/a/mycube and ~/b/mycube: one folder name, two datasets (the second with another gravity)."""
    first = write_recordings(tmp_path / "a" / "mycube", falling_cubes(seed=1))
    other = falling_cubes(seed=1)
    other.meta["gravity"] = [0.0, 0.0, -5.0]
    second = write_recordings(tmp_path / "b" / "mycube", other)
    return first, second


# ---------------------------------------------------------------- nothing overwrites anything else


def test_two_datasets_with_one_folder_name_keep_separate_results(tmp_path):
    folders = two_cubes_named_alike(tmp_path)
    written = []
    for folder in folders:
        cfg, run_dir = composed("evaluate", ["dataset=recordings", f"recordings={folder}"], tmp_path)
        written.append(run_dir / "metrics.json")
        runs.evaluate(cfg, run_dir)
    assert written[0] != written[1] and all(path.is_file() for path in written)
    variants = [json.loads(path.read_text())["variant"] for path in written]
    assert variants[0] != variants[1] and all(variant.startswith("mycube") for variant in variants)
    # train.py and diagnose.py file them apart too, and evaluate.py finds each one's own train run
    trains = [composed("train", ["dataset=recordings", f"recordings={f}"], tmp_path)[1] for f in folders]
    diagnoses = [composed("diagnose", [f"recordings={f}"], tmp_path)[1] for f in folders]
    assert trains[0] != trains[1] and diagnoses[0] != diagnoses[1]
    for folder, train_dir in zip(folders, trains):
        cfg, _ = composed("evaluate", ["dataset=recordings", f"recordings={folder}"], tmp_path)
        assert Path(cfg.train_dir) == train_dir
    # the same data under another path is the same dataset: one key, read from the files, not from the path
    copy = write_recordings(tmp_path / "c" / "mycube", falling_cubes(seed=1))
    assert composed("train", ["dataset=recordings", f"recordings={copy}"], tmp_path)[1] == trains[0]


def test_a_refused_run_says_which_setting_differs_and_its_advice_works(tmp_path):
    folder = write_recordings(tmp_path / "cubes", falling_cubes())
    base = ["dataset=recordings", f"recordings={folder}", "budget=smoke"]
    cfg, run_dir = composed("train", base, tmp_path)
    runs.train(cfg, run_dir)
    other, same_dir = composed("train", [*base, "context_frames=5"], tmp_path)
    assert same_dir == run_dir  # context_frames is not in the folder's name: this command meets the other run
    with pytest.raises(ContactbenchError) as refused:
        runs.train(other, run_dir)
    message = str(refused.value)
    assert "context_frames: 6 there, 5 here" in message and "\n" not in message
    assert "hydra.run.dir=" in message  # train.py writes wherever hydra.run.dir says
    runs.train(other, tmp_path / "elsewhere")
    # evaluate.py's train_dir holds the other run: it finds this one through the run index, or names train_dir=
    evaluation, eval_dir = composed("evaluate", [*base, "context_frames=5", "split=val"], tmp_path)
    assert runs.evaluate(evaluation, eval_dir)["context_frames"] == 5
    unfitted, _ = composed("evaluate", [*base, "context_frames=4", "split=val"], tmp_path)
    with pytest.raises(ContactbenchError) as refused:
        runs.evaluate(unfitted, tmp_path / "eval4")
    message = str(refused.value)
    assert "context_frames: 6 there, 4 here" in message and "train_dir=" in message
    assert "hydra.run.dir" not in message  # it names where evaluate.py writes, not which model it scores
    trained, _ = composed("train", [*base, "context_frames=4"], tmp_path)
    runs.train(trained, tmp_path / "fitted4")
    named, _ = composed("evaluate", [*base, "context_frames=4", "split=val", f"train_dir={tmp_path}/fitted4"], tmp_path)
    assert runs.evaluate(named, tmp_path / "eval4")["context_frames"] == 4


def test_a_run_that_fails_before_fitting_leaves_nothing_that_blocks_the_next(tmp_path):
    folder = write_recordings(tmp_path / "cubes", falling_cubes())
    base = ["dataset=recordings", f"recordings={folder}", "budget=smoke"]
    broken, run_dir = composed("train", [*base, f"model.contact_model._target_={__name__}.TakesNoArguments"], tmp_path)
    with pytest.raises(Exception, match="TakesNoArguments"):
        runs.train(broken, run_dir)
    assert not (run_dir / "signature.json").exists()
    fixed, same_dir = composed("train", base, tmp_path)
    assert same_dir == run_dir
    runs.train(fixed, run_dir)  # resume=true, the default: no signature of the failed run stands in the way
    assert (run_dir / "signature.json").is_file() and (run_dir / "val" / "metrics.json").is_file()


def test_a_generated_dataset_is_said_in_one_line_and_a_custom_value_is_marked(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    cfg, run_dir = composed("evaluate", ["dataset=frictioncubes", "friction=0.3", SMALL], tmp_path)
    document = runs.evaluate(cfg, run_dir)
    said = [record for record in caplog.records if "generating" in record.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.WARNING, [r.getMessage() for r in said]
    assert f"{tmp_path}/data/frictioncubes/friction=0.3" in said[0].getMessage()
    assert "not a paper variant" in said[0].getMessage()
    scored = [record.getMessage() for record in caplog.records if "pos_err" in record.getMessage()]
    assert len(scored) == 1 and "friction=0.3 (not a paper variant)" in scored[0]
    assert document["paper_variant"] is False and document["budget"] == "quick" and document["task"] == "evaluate"
    from contactbench.evaluation.renders import rerun

    (run_dir / ".hydra").mkdir()  # what a Hydra job records (a composed config here)
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    assert rerun([run_dir]).label == "frictioncubes friction=0.3 (not a paper variant)"  # a render's title


# ---------------------------------------------------------------- the report says what it mixes


def write_row(root: Path, folder: str, **fields) -> Path:
    """A test or val metrics.json (and per_trajectory.csv) as train.py or evaluate.py writes it, in root/folder."""
    summary = {
        "model": "mujoco_default",
        "dataset": "frictioncubes",
        "variant": "friction=0",
        "split": "test",
        "n_trajectories": 2,
        "context_frames": 6,
        "noise_mm": 0.0,
        "frame_stride": 1,
        "seed": 0,
        "variant_values": {"friction": 0.0},
        "pos_err": 0.2,
        "rot_err_rad": 0.3,
        "floor_penetration_m": 1e-4,
        "interbody_penetration_m": 0.0,
        "pairwise_collisions": 0.0,
        "per_frame": {"frame": [0, 1], "pos_err": [0.1, 0.3], "rot_err_rad": [0.2, 0.4]},
        **fields,
    }
    path = root / folder / "metrics.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(summary))
    with open(path.parent / "per_trajectory.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["trajectory", "pos_err", "rot_err_rad", "floor_penetration_m"])
        writer.writerows([[0, summary["pos_err"], summary["rot_err_rad"], 1e-4]] * 2)
    return path


def section(text: str, title: str) -> str:
    return re.search(rf"^## {re.escape(title)}.*?\n(.*?)(?=^## |\Z)", text, re.S | re.M).group(1)


def test_the_report_names_budget_seed_and_source_and_warns_when_a_table_mixes_budgets(tmp_path):
    write_row(tmp_path, "train/sysid/run_q/test", model="sysid", budget="quick", task="train", pos_err=0.15)
    write_row(tmp_path, "train/sysid/run_s/test", model="sysid", budget="smoke", task="train", pos_err=0.25)
    write_row(tmp_path, "evaluate/mujoco_default/budget=quick,seed=0,split=test", budget="quick", task="evaluate")
    text = write_report(tmp_path, renders=False).read_text()
    every = section(text, "Every run")
    assert re.search(r"^\| model \| dataset \| variant \| split \| seed \|.*\| budget \| source run \|$", every, re.M)
    assert re.search(
        r"^\| sysid \| frictioncubes \| friction=0 \| test \| 0 \|.*\| smoke \| train.py: "
        r"train/sysid/run_s \|$",
        every,
        re.M,
    )
    assert "| quick | evaluate.py: evaluate/mujoco_default/budget=quick,seed=0,split=test |" in every
    grid = section(text, "Test position error")
    assert "| dataset | variant | budget | mujoco_default | sysid | not significant (95%) |" in grid
    # not averaged with the quick fit, and alone in its row: nothing to compare
    assert "| frictioncubes | friction=0 | smoke | – | 0.250 [0.250–0.250] / 0.300 [0.300–0.300] | – |" in grid
    (warning,) = [line for line in grid.splitlines() if "more than one budget" in line]
    assert "quick" in warning and "smoke" in warning


def test_a_test_row_scored_by_train_and_by_evaluate_is_shown_once(tmp_path):
    folder = write_recordings(tmp_path / "cubes", falling_cubes())
    base = ["dataset=recordings", f"recordings={folder}", "budget=smoke"]
    cfg, train_dir = composed("train", [*base, "test=true"], tmp_path)
    runs.train(cfg, train_dir)
    cfg, eval_dir = composed("evaluate", base, tmp_path)
    runs.evaluate(cfg, eval_dir)
    outputs = tmp_path / "outputs"
    text = write_report(outputs, renders=False).read_text()
    every = section(text, "Every run")
    assert len(re.findall(r"^\| mujoco_default \| recordings \| .* \| test \|", every, re.M)) == 1
    kept = f"train.py: {train_dir.relative_to(outputs)}"
    assert f"| {kept} |" in every
    (said,) = [line for line in text.splitlines() if "scored twice" in line.lower()]
    assert str(eval_dir.relative_to(outputs)) in said and "train.py" in said


def test_table3_leaves_out_what_is_not_a_paper_variant(tmp_path):
    write_row(tmp_path, "a/test", budget="quick", task="evaluate")
    write_row(
        tmp_path,
        "b/test",
        budget="quick",
        task="evaluate",
        variant="friction=0.3",
        variant_values={"friction": 0.3},
        pos_err=0.6,
    )
    text = write_report(tmp_path, renders=False).read_text()
    assert "| frictioncubes | friction=0.3 (not a paper variant) | quick |" in section(text, "Test position error")
    assert "| friction=0.3 (not a paper variant) | test |" in section(text, "Every run")
    table3 = section(text, "Table 3, recomputed")
    assert not re.search(r"^\| mujoco_default \| (Yes|No) \|", table3, re.M)  # one paper variant: nothing to compare
    assert "frictioncubes friction=0.3 (not a paper variant)" in table3
    with open(tmp_path / "results" / "quick.csv", newline="") as handle:
        marked = {row["variant"]: row["paper_variant"] for row in csv.DictReader(handle)}
    assert marked["friction=0.3"] == "no" and marked[next(v for v in marked if v != "friction=0.3")] == "yes"


def test_the_papers_figures_leave_out_what_is_not_a_paper_variant(tmp_path, monkeypatch):
    from contactbench.evaluation import figures, plotting

    for value in (0.0, 0.5, 0.3):
        variant = f"friction={value:g}"
        write_row(tmp_path, f"{value:g}/test", task="evaluate", variant=variant, variant_values={"friction": value})
    drawn, swept = {}, {}
    save, sweep = figures.save_figure, figures.sweep_figure

    def recorded_save(figure, path):
        drawn[path.name] = [title.get_text().replace("\n", " ") for title in plotting.titles(figure)]
        return save(figure, path)

    def recorded_sweep(runs, dataset, path):
        swept[dataset] = sorted(run.summary["variant"] for run in runs if run.summary["dataset"] == dataset)
        return sweep(runs, dataset, path)

    monkeypatch.setattr(figures, "save_figure", recorded_save)
    monkeypatch.setattr(figures, "sweep_figure", recorded_sweep)
    text = write_report(tmp_path, renders=False).read_text()
    assert swept["frictioncubes"] == ["friction=0", "friction=0.5"]  # Fig. 2 draws the paper's variants only
    assert "frictioncubes.png" in drawn
    assert "friction=0.3 (not a paper variant)" in drawn["error_over_time_frictioncubes.png"]
    (said,) = [line for line in section(text, "Figures").splitlines() if line.startswith("Left out")]
    assert "frictioncubes friction=0.3 (not a paper variant)" in said


def test_a_figure_of_two_budgets_draws_a_line_per_model_and_budget(tmp_path, monkeypatch):
    from contactbench.evaluation import figures

    write_row(tmp_path, "q/test", model="sysid", budget="quick", task="train", pos_err=0.15)
    write_row(tmp_path, "s/test", model="sysid", budget="smoke", task="train", pos_err=0.25)
    legends, save = {}, figures.save_figure

    def recorded_save(figure, path):
        legends[path.name] = sorted(
            text.get_text() for axis in figure.axes if axis.get_legend() for text in axis.get_legend().get_texts()
        )
        return save(figure, path)

    monkeypatch.setattr(figures, "save_figure", recorded_save)
    write_report(tmp_path, renders=False)
    assert legends["error_over_time_frictioncubes.png"] == ["sysid (quick)", "sysid (smoke)"]
    assert legends["frictioncubes.png"] == ["sysid (quick)", "sysid (smoke)"]
