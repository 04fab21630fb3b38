"""The residual model's stage one takes a finished model=sysid run of the same settings from the run tree instead of
repeating its search, and searches when the run there differs in anything that makes the fit."""

from __future__ import annotations

import json
import logging

import pytest
from test_pipeline import compose_config

from contactbench import runs
from contactbench.folders import SIGNATURE, run_signature
from contactbench.models.residual import stage_one
from contactbench.models.residual.module import ResidualModule

OVERRIDES = ["dataset=contactnets_cube", "budget=smoke"]
NAMES = ["object_friction_0", "floor_friction", "floor_stiffness", "floor_damping"]


@pytest.fixture(scope="module")
def sysid_tree(tmp_path_factory):
    """A run tree holding one finished model=sysid run at budget=smoke on the real cube."""
    root = tmp_path_factory.mktemp("tree")
    run = root / "outputs" / "multirun" / "model=sysid"
    runs.train(compose_config("train", [*OVERRIDES, "model=sysid"], root), run)
    return root, run


def residual_fields(root, overrides=()):
    """The residual run's signature and the SysID module fields its stage one would run, as composed."""
    cfg = compose_config("train", [*OVERRIDES, "model=residual", *overrides], root)
    module = cfg.model.module
    fields = stage_one.sysid_module_fields(dict(module.sysid), int(module.seed), module.nthread, int(module.substeps))
    return json.loads(json.dumps(run_signature(cfg))), fields, str(module.sysid_runs)


def test_the_residual_takes_the_sweeps_sysid_fit_instead_of_searching(sysid_tree, monkeypatch, caplog):
    root, sysid_run = sysid_tree

    def searched(self):
        raise AssertionError("stage one searched although a finished sysid run of the same settings was there")

    monkeypatch.setattr(ResidualModule, "_search", searched)
    residual_run = root / "outputs" / "multirun" / "model=residual"
    with caplog.at_level(logging.INFO, logger="contactbench.models.residual.module"):
        runs.train(compose_config("train", [*OVERRIDES, "model=residual"], root), residual_run)
    said = [record.getMessage() for record in caplog.records if "stage one" in record.getMessage()]
    assert said == [
        f"residual: stage one took the SysID fit of {sysid_run.resolve()} (same settings; its search not repeated)"
    ]
    sysid = json.loads((sysid_run / "fitted.json").read_text())
    residual = json.loads((residual_run / "fitted.json").read_text())
    assert residual["parameters"] == sysid["parameters"]  # bit for bit: JSON keeps a float64 exactly
    assert residual["sysid_run"] == str(sysid_run.resolve())


def test_a_sysid_run_of_other_settings_is_not_taken(sysid_tree):
    root, sysid_run = sysid_tree
    signature, fields, runs_dir = residual_fields(root)
    found = stage_one.finished_sysid_run(runs_dir, signature, fields, NAMES)
    assert isinstance(found, stage_one.Reused) and found.run == sysid_run.resolve()
    # another search budget, seed, eq. (1) exponent or observation: the fit would differ, so the search runs
    for overrides in (
        ["model.budgets.smoke.search.evaluations=8"],
        ["seed=1"],
        ["model.module.sysid.position_exponent=1"],
        ["observation.noise_mm=1"],
        ["context_frames=4"],
    ):
        other_signature, other_fields, _ = residual_fields(root, overrides)
        missed = stage_one.finished_sysid_run(runs_dir, other_signature, other_fields, NAMES)
        assert isinstance(missed, str) and "no finished model=sysid run" in missed, overrides
    assert "null" in stage_one.finished_sysid_run(None, signature, fields, NAMES)
    assert "no signature.json" in stage_one.finished_sysid_run(runs_dir, None, fields, NAMES)


def test_a_sysid_run_whose_files_are_not_a_finished_fit_is_not_taken(sysid_tree, tmp_path):
    root, sysid_run = sysid_tree
    signature, fields, runs_dir = residual_fields(root)
    fitted_path = sysid_run / "fitted.json"
    original = fitted_path.read_text()
    fitted = json.loads(original)
    try:
        for broken in (
            {**fitted, "parameters": {**fitted["parameters"], "floor_friction": "0.5"}},  # not a number
            {**fitted, "parameters": {name: fitted["parameters"][name] for name in NAMES[1:]}},  # one missing
            {**fitted, "model": "sysid_bullet"},
        ):
            fitted_path.write_text(json.dumps(broken))
            assert isinstance(stage_one.finished_sysid_run(runs_dir, signature, fields, NAMES), str)
        fitted_path.write_text("not json {")
        assert isinstance(stage_one.finished_sysid_run(runs_dir, signature, fields, NAMES), str)
        fitted_path.unlink()  # still fitting: no fitted.json yet
        assert isinstance(stage_one.finished_sysid_run(runs_dir, signature, fields, NAMES), str)
    finally:
        fitted_path.write_text(original)
    # a signature edited to another engine's module is not the residual's search either
    recorded = json.loads((sysid_run / SIGNATURE).read_text())
    recorded["model"]["module"]["engine"] = "bullet"
    assert not stage_one._same_settings(recorded, signature, fields)
