"""Every config in conf/ composes, resolves and names importable classes (after lightning-hydra-template's
test_configs): each entry config with each option of each config group it uses, and every model with every budget.

Cheap, side-effect-free parts are instantiated (scenes, analytical models, callbacks, the CPU trainer, the file
loggers); models, data modules and the remote loggers are only checked to be importable (they need data or a
service). Nothing here reads a dataset or starts a run.
"""

from __future__ import annotations

import fnmatch
from pathlib import Path

import pytest
from conftest import falling_cubes
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, Glob
from hydra.utils import get_class, get_object, instantiate
from omegaconf import DictConfig, OmegaConf

from contactbench import fitting
from contactbench.config import CONFIG_DIR

ENTRIES = ["train", "evaluate", "generate", "diagnose"]


def options(group: str) -> list[str]:
    return sorted(path.stem for path in (CONFIG_DIR / group).glob("*.yaml"))


def entry_groups(entry: str) -> list[str]:
    """The config groups an entry config selects in its defaults list (paths, budget, model, ...)."""
    defaults = OmegaConf.load(CONFIG_DIR / f"{entry}.yaml").defaults
    groups = [next(iter(item)) for item in defaults if isinstance(item, DictConfig)]
    return [group for group in groups if (CONFIG_DIR / group).is_dir()]


def cases(entry: str) -> list[list[str]]:
    """Override lists: the defaults, each option of each group the entry uses, each launcher; for train (evaluate
    composes the same model and budget nodes) every model with every budget, since each model's config holds its
    numbers for every budget."""
    found = [[]]
    for group in entry_groups(entry):
        found += [[f"{group}={option}"] for option in options(group)]
    if entry == "train":
        found += [[f"model={m}", f"budget={b}"] for m in options("model") for b in options("budget")]
    found += [[f"hydra/launcher={launcher}"] for launcher in options("hydra/launcher")]
    return found


@pytest.fixture(scope="module")
def hydra_configs():
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        yield
    GlobalHydra.instance().clear()


def targets(node) -> list[str]:
    """Every _target_ in a config tree."""
    if isinstance(node, dict):
        found = [node["_target_"]] if "_target_" in node else []
        return found + [t for value in node.values() for t in targets(value)]
    if isinstance(node, list):
        return [t for value in node for t in targets(value)]
    return []


def test_every_group_option_is_covered():
    listed = [overrides for entry in ENTRIES for overrides in cases(entry)]
    for group in ("model", "dataset", "variant", "budget", "logger", "trainer", "generation", "paths", "experiment"):
        for option in options(group):
            assert any(f"{group}={option}" in overrides for overrides in listed), (group, option)
    assert {"model", "dataset", "variant", "budget", "trainer", "logger"} <= set(entry_groups("train"))
    assert {"budget", "paths"} <= set(entry_groups("diagnose"))


@pytest.mark.parametrize("experiment", options("experiment"))
def test_an_experiment_sweeps_over_options_that_exist(experiment: str, hydra_configs):
    params = OmegaConf.load(CONFIG_DIR / "experiment" / f"{experiment}.yaml").hydra.sweeper.params
    assert {"model", "variant"} <= set(params)
    train = compose(config_name="train")
    for key, values in params.items():
        if key in ("model", "variant"):  # config groups: every value an option, every glob pattern one at least
            sweep = OverridesParser.create().parse_overrides([f"{key}={values}"])[0].value()
            if isinstance(sweep, Glob):
                assert all(fnmatch.filter(options(key), pattern) for pattern in sweep.include), (experiment, values)
                chosen = sweep.filter(options(key))
            else:
                chosen = list(sweep.list) if isinstance(sweep, ChoiceSweep) else [str(sweep)]
            assert chosen and set(chosen) <= set(options(key)), (experiment, key, values)
        else:  # a setting train.py's config has
            assert OmegaConf.select(train, key) is not None, (experiment, key)


@pytest.mark.parametrize("entry", ENTRIES)
def test_every_config_composes_resolves_and_instantiates(entry: str, hydra_configs, tmp_path: Path):
    for overrides in cases(entry):
        needs_recordings = entry == "diagnose" or "dataset=recordings" in overrides
        extra = [f"recordings={tmp_path / 'some recordings'}"] if needs_recordings else []
        launcher = any(o.startswith("hydra/launcher=") for o in overrides)
        cfg = compose(
            config_name=entry,
            overrides=[f"paths.log_dir={tmp_path}/outputs", f"paths.data_dir={tmp_path}/data", *overrides, *extra],
            return_hydra_config=launcher,
        )
        where = f"{entry} {' '.join(overrides)}"
        if launcher:  # hydra's own node needs a running job to resolve; its launcher class must import
            get_class(cfg.hydra.launcher._target_)
            continue
        resolved = OmegaConf.to_container(cfg, resolve=True)  # every interpolation and resolver
        for target in targets(resolved):
            assert callable(get_object(target)), f"{where}: {target}"
        check_instantiable(cfg, tmp_path, where)


def check_instantiable(cfg: DictConfig, tmp_path: Path, where: str) -> None:
    if cfg.get("dataset") is not None and cfg.dataset.scene is not None:
        instantiate(cfg.dataset.scene)
    model = cfg.get("model")
    if model is not None:
        if model.kind == "analytical":
            contact_model = instantiate(model.contact_model)
            contact_model.contact_parameters(falling_cubes(1, 8))  # its preset names parameters its engine has
        else:
            assert model.kind == "lightning", where
            callbacks = fitting.make_callbacks(model, tmp_path / "checkpoints")
            if cfg.get("trainer") is not None and cfg.trainer.accelerator == "cpu":
                instantiate(
                    cfg.trainer,
                    **model.get("trainer", {}),
                    callbacks=callbacks,
                    logger=False,
                    default_root_dir=str(tmp_path / "run"),
                )
    logger = cfg.get("logger")
    if logger is not None and logger._target_.endswith(("CSVLogger", "TensorBoardLogger")):
        instantiate(logger, save_dir=str(tmp_path / "run"))


def test_a_tuned_setting_applies_to_its_model_and_dataset_only_and_evaluate_finds_the_run(hydra_configs, tmp_path):
    """tuned/<model>_<dataset>.yaml (here a user's own, on hydra.searchpath) changes that model on that dataset only,
    and evaluate.py composes the same settings; what val can choose (the GNN's noise) is chosen in the fit instead."""
    from contactbench.folders import signature_key

    (tmp_path / "tuned").mkdir()
    (tmp_path / "tuned" / "gnn_contactnets_cube.yaml").write_text(
        "# @package _global_\nmodel:\n  module:\n    lr: 5.0e-4\n"
    )
    search = f"hydra.searchpath=[file://{tmp_path}]"
    train = compose("train", overrides=[search, "model=gnn", "dataset=contactnets_cube"])
    assert train.model.module.lr == 5.0e-4
    assert compose("train", overrides=[search, "model=gnn", "dataset=frictioncubes"]).model.module.lr != 5.0e-4
    assert compose("train", overrides=[search, "model=gnn_paper", "dataset=contactnets_cube"]).model.module.lr != 5.0e-4
    evaluate = compose("evaluate", overrides=[search, "model=gnn", "dataset=contactnets_cube"])
    assert signature_key(train) == signature_key(evaluate)  # evaluate.py finds what train.py fitted
    noise_grid = compose("train", overrides=["model=gnn"]).model.choose_on_val.module.noise_std
    assert list(noise_grid) == [1.0e-4, 2.0e-4, 4.0e-4]


@pytest.mark.parametrize(
    ("overrides", "skipped"),
    [
        (["variant=contactnets_cube"], False),  # a recorded dataset's variant is the dataset itself
        (["variant=frictioncubes_0.5"], False),
        (["dataset=frictioncubes", "variant=polyhedra_8"], True),  # -m dataset=a,b 'variant=glob(*)' crosses them
    ],
)
def test_a_sweep_skips_a_variant_of_another_dataset_only(overrides, skipped, hydra_configs):
    from hydra.core.hydra_config import HydraConfig

    from contactbench.runs import crossed_variant

    cfg = compose("generate", overrides=overrides, return_hydra_config=True)
    HydraConfig.instance().set_config(cfg)
    try:
        assert crossed_variant(cfg) is skipped
    finally:
        HydraConfig.instance().cfg = None
