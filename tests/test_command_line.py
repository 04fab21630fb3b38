"""A command line written the way other tools take options (`dataset contactnets_cube`, `--model sysid`) or a
dataset's setting without its dataset is one line that says what to write instead."""

from __future__ import annotations

import pytest
from test_pipeline import run_entry_point

from contactbench import cli


@pytest.mark.parametrize(
    "task, arguments, line",
    [
        (
            "train",
            ["dataset", "contactnets_cube"],
            "dataset contactnets_cube: write key=value (dataset=contactnets_cube)",
        ),
        ("train", ["model", "sysid", "budget=smoke"], "model sysid: write key=value (model=sysid)"),
        ("train", ["--model", "sysid"], "--model sysid: write key=value, without dashes (model=sysid)"),
        ("evaluate", ["--model=sysid"], "--model=sysid: write key=value, without dashes (model=sysid)"),
        ("train", ["friction", "0.3"], "friction 0.3: write key=value (friction=0.3)"),
        ("train", ["sysid"], "sysid: write key=value (model=sysid)"),
        ("train", ["budget=smoke", "dataset"], "dataset: write key=value (dataset=...)"),
        (
            "train",
            ["recordings=assets/contactnets_cube"],
            "recordings=assets/contactnets_cube: recordings is a setting of dataset=recordings "
            "(write dataset=recordings recordings=assets/contactnets_cube)",
        ),
        (
            "evaluate",
            ["ground=ramp"],
            "ground=ramp: ground is a setting of dataset=terrain (write dataset=terrain ground=ramp)",
        ),
        (
            "train",
            ["dataset=bouncycubes", "friction=0.3"],
            "friction=0.3: friction is a setting of dataset=frictioncubes (write dataset=frictioncubes friction=0.3)",
        ),
        (
            "diagnose",
            ["dataset=contactnets_cube"],
            "dataset=contactnets_cube: diagnose.py reads a recordings folder, not a dataset "
            "(write recordings=<folder>, e.g. recordings=assets/contactnets_cube)",
        ),
        ("diagnose", ["model=sysid"], "model=sysid: diagnose.py takes no model (python diagnose.py --help lists"),
    ],
)
def test_a_command_line_in_another_style_says_how_to_write_it(capsys, task, arguments, line):
    with pytest.raises(SystemExit) as stopped:
        cli.check_command_line(task, arguments)
    err = capsys.readouterr().err
    assert stopped.value.code == 2 and err.startswith(f"error: {line}") and len(err.strip().splitlines()) == 1, err
    assert "+" not in err


@pytest.mark.parametrize(
    "task, arguments",
    [
        ("train", ["~logger"]),  # Hydra's delete syntax has no '='
        ("train", ["--cfg", "job", "model=sysid"]),
        ("train", ["-m", "model=sysid,gnn"]),
        ("train", ["dataset=recordings", "recordings=assets/contactnets_cube"]),
        ("diagnose", ["recordings=assets/contactnets_cube"]),
        ("train", ["--help"]),
    ],
)
def test_commands_written_key_value_pass(capsys, task, arguments):
    cli.check_command_line(task, arguments)
    assert capsys.readouterr().err == ""


def test_a_missing_equals_sign_is_one_line_from_the_entry_point(tmp_path):
    result = run_entry_point("train.py", ["dataset", "contactnets_cube"], tmp_path, timeout=120)
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.strip() == "error: dataset contactnets_cube: write key=value (dataset=contactnets_cube)"
    assert not (tmp_path / "outputs").exists()
