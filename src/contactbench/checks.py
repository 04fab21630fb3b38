"""The one check of a composed config, before a command does anything: an impossible setting is one clear line, not a
run. (A command line Hydra cannot compose at all is cli.check_command_line's, before this.)

What is checked, and by what:
- unset mandatory values (`???`) and a `+key=...` nothing reads: by the config's tree and the command line;
- the run settings: `context_frames` and `torch_threads` by RUN_SETTINGS, the observation by its own dataclass;
- every budget number, by BUDGET_RULES (by name, wherever it appears in the budget the run uses: budget.diagnose and
  the model's budgets.<budget name>, however deep, so a model of one's own is checked too);
- the dataset's scene, by its spec's own checks (generation/scenes.py).

Hydra names the run folder from the config before the command starts (a recordings folder's hash, the budget's
name...): `CheckBeforeRun` refuses what would make that fail or mislead first, the same way `check` does."""

from __future__ import annotations

import difflib
import logging
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass

from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import OverrideType
from hydra.errors import InstantiationException
from hydra.experimental.callback import Callback
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from contactbench import variants
from contactbench.config import CONFIG_DIR
from contactbench.errors import ContactbenchError
from contactbench.observation import Observation

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Rule:
    """What a setting must be: `expected` is what the error says, `accepts` the test."""

    expected: str
    accepts: Callable[[object], bool]


def _integer(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


COUNT = Rule("a positive integer", lambda value: _integer(value) and value >= 1)
COUNT_OR_ALL = Rule("a positive integer or null (all)", lambda value: value is None or COUNT.accepts(value))
RATE = Rule("a positive number", lambda value: _number(value) and value > 0)

# Budget numbers by name. A key not listed here is not refused for being unknown.
BUDGET_RULES = {
    **dict.fromkeys(
        (
            "evaluations",
            "restarts",
            "num_workers",
            "max_steps",
            "val_check_interval",
            "max_epochs",
            "patience",
            "segments_per_epoch",
            "val_segments",
            "segment_frames",
            "fit_trajectories",
            "law_trajectories",
            "law_evaluations",
            "base_evaluations",
            "batch",
            "lsq_iterations",
            "front_runners",
            "max_effects",
            "bootstrap",
            "batch_trajectories",
            "val_trajectories",
            "interval_trajectories",
            "val_rollouts",
            "val_windows",
            "batch_size",
            "batch_vertices",
            "latent_size",
            "message_passing_steps",
        ),
        COUNT,
    ),
    "lr": RATE,
}
# In a model's budgets these may also be null: every trajectory (the diagnosis always samples).
MODEL_BUDGET_RULES = {
    **BUDGET_RULES,
    **dict.fromkeys(("batch_trajectories", "val_trajectories", "interval_trajectories", "val_rollouts"), COUNT_OR_ALL),
}
# Top-level settings, where the command has them.
THREADS = Rule("a positive integer or null (torch's choice)", lambda value: value is None or COUNT.accepts(value))
RUN_SETTINGS = {"context_frames": COUNT, "torch_threads": THREADS}
# Top-level keys no config file sets that the code reads when given (+effects=[floor_tilt] for generate, ...).
OPTIONAL_KEYS = ("effects", "effect_strength", "overwrite", "resume", "torch_threads")


def check(cfg: DictConfig) -> None:
    """Refuse what `before_run` refuses, impossible run settings and budgets, and physically impossible scenes
    (ContactbenchError)."""
    refused = before_run(cfg)
    if refused:
        raise ContactbenchError(refused)
    for key, rule in RUN_SETTINGS.items():
        if key in cfg:
            _apply(rule, cfg[key], key)
    if cfg.get("observation") is not None:
        Observation.of(cfg.observation)  # its own checks say what is wrong
    budget = cfg.get("budget")
    if budget is not None:
        _check_budget(budget.get("diagnose"), "budget.diagnose", BUDGET_RULES)
        model = cfg.get("model")
        if model is not None and model.get("budgets") is not None:
            if budget.name not in model.budgets:
                raise ContactbenchError(
                    f"model {model.name} has no budget {budget.name!r} (expected one of "
                    f"{', '.join(model.budgets)} in its config's budgets)"
                )
            _check_budget(model.budgets[budget.name], f"model.budgets.{budget.name}", MODEL_BUDGET_RULES)
    dataset = cfg.get("dataset")
    if dataset is not None and dataset.get("scene") is not None:
        _check_scene(cfg)


def before_run(config: DictConfig) -> str | None:
    """What must be refused before the config is resolved (resolving would fail on it, or name a folder after it):
    an unset mandatory value, or a `+key` nothing reads. The message, or None."""
    missing = missing_keys(config)
    if missing:
        return f"{missing[0]} is not set (expected {missing[0]}=... on the command line)"
    return unknown_addition(config, task_overrides(config))


class CheckBeforeRun(Callback):
    """`before_run`, as a Hydra callback (conf/hydra/default.yaml): before Hydra names the run folder."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        _exit_if_refused(config)

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        _exit_if_refused(config)


def _exit_if_refused(config: DictConfig) -> None:
    refused = before_run(config)
    if refused:  # outside the command's guard (cli.guarded): said here, as it says it
        print(f"error: {refused}", file=sys.stderr)
        sys.exit(2)


def missing_keys(config: DictConfig) -> list[str]:
    """Keys left at '???' outside Hydra's own node, found without resolving (resolving would fail on them)."""
    tree = OmegaConf.to_container(config, resolve=False, throw_on_missing=False)
    tree.pop("hydra", None)
    return _missing(tree, "")


def task_overrides(config: DictConfig) -> list[str]:
    """The command line's overrides: from the config's hydra node when it has one, else from the running Hydra app."""
    if "hydra" in config:
        return list(OmegaConf.select(config, "hydra.overrides.task", default=None) or [])
    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


def unknown_addition(config: DictConfig, overrides: list[str]) -> str | None:
    """The message for a `+key=value` that adds a top-level key nothing reads (a misspelling), or None.

    A `+` override can only add a key that no config file sets, so it is read only when it is one of OPTIONAL_KEYS
    or a config group (conf/<group>/); everything else would be ignored silently. `++key=...` (force) is left alone.
    """
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except Exception:  # Hydra itself reports a malformed override
        return None
    groups = {path.name for path in CONFIG_DIR.iterdir() if path.is_dir()}
    task = config.get("task_name", "this command")
    for override in parsed:
        key = override.key_or_group
        if override.type != OverrideType.ADD or "." in key or "@" in key or key in OPTIONAL_KEYS or key in groups:
            continue
        present = [name for name in config if name != "hydra" and name != key] + list(OPTIONAL_KEYS)
        close = difflib.get_close_matches(key, present, n=1)
        hint = f"did you mean {close[0]}=...? " if close else ""
        return (
            f"+{key}=... adds a setting {task} does not read ({hint}expected an existing key, set without '+', "
            f"or one of {', '.join(OPTIONAL_KEYS)})"
        )
    return None


def _missing(tree, prefix: str) -> list[str]:
    if isinstance(tree, dict):
        return [key for name, value in tree.items() for key in _missing(value, f"{prefix}{name}.")]
    if isinstance(tree, list):
        return [key for k, value in enumerate(tree) for key in _missing(value, f"{prefix}{k}.")]
    return [prefix[:-1]] if tree == "???" else []


def _apply(rule: Rule, value: object, where: str) -> None:
    if not rule.accepts(value):
        raise ContactbenchError(f"{where} is {value!r} (expected {rule.expected})")


def _check_budget(node: DictConfig | None, where: str, rules: dict[str, Rule]) -> None:
    if not isinstance(node, DictConfig):
        return
    for key in node:
        if isinstance(node.get(key), DictConfig):
            _check_budget(node[key], f"{where}.{key}", rules)
        elif key in rules:
            _apply(rules[key], node[key], f"{where}.{key}")


def _check_scene(cfg: DictConfig) -> None:
    """Build the scene spec (its own checks say what is physical) and say when a variant is not one of Table 1's."""
    try:
        instantiate(cfg.dataset.scene)
    except InstantiationException as error:
        # instantiate wraps what the target raised; the spec's own message is the one for the user.
        if isinstance(error.__cause__, ContactbenchError):
            raise error.__cause__ from None
        raise
    variant = str(cfg.dataset.variant)
    if variants.paper_variant(cfg.dataset.name, variant) is not True:
        log.warning(
            "%s %s is a custom variant, not one of the paper's Table 1 variants (conf/variant/): its results say '%s'"
            " and stay out of the report's Table 3",
            cfg.dataset.name,
            variant,
            variants.NOT_PAPER,
        )
