"""Checks of a composed config before a command does anything: an impossible setting is one clear error, not a run."""

from __future__ import annotations

import difflib
import logging
import math

from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import OverrideType
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from contactbench import variants
from contactbench.config import CONFIG_DIR
from contactbench.errors import ContactbenchError

log = logging.getLogger(__name__)

# Budget counts that must be positive integers, those that may also be null (meaning "all"), and rates: checked by
# name wherever they appear in the budget the run uses (budget.diagnose and the model's own budgets.<budget name>,
# however deep), so a model of one's own is checked too. A key not listed here is not refused for being unknown.
COUNTS = (
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
    "base_evaluations",
    "batch",
    "lsq_iterations",
    "front_runners",
    "max_effects",
    "bootstrap",
    "batch_trajectories",
    "val_trajectories",
    "val_rollouts",
    "val_windows",
    "batch_size",
    "batch_vertices",
    "latent_size",
    "message_passing_steps",
)
# In a model's budgets these may also be null: every trajectory (the diagnosis always samples).
COUNTS_OR_ALL = ("batch_trajectories", "val_trajectories", "val_rollouts")
RATES = ("lr",)
# Top-level keys no config file sets that the code reads when given (+effects=[floor_tilt] for generate, ...).
OPTIONAL_KEYS = ("effects", "effect_strength", "overwrite", "resume", "torch_threads")


def check(cfg: DictConfig) -> None:
    """Refuse unset mandatory values, non-positive budgets and physically impossible scenes (ContactbenchError)."""
    missing = missing_keys(cfg)
    if missing:
        raise ContactbenchError(f"{missing[0]} is not set (expected {missing[0]}=... on the command line)")
    unknown = unknown_addition(cfg, task_overrides(cfg))
    if unknown:
        raise ContactbenchError(unknown)
    budget = cfg.get("budget")
    if budget is not None:
        _check_budget(budget.get("diagnose"), "budget.diagnose", or_all=())
        model = cfg.get("model")
        if model is not None and model.get("budgets") is not None:
            if budget.name not in model.budgets:
                raise ContactbenchError(
                    f"model {model.name} has no budget {budget.name!r} (expected one of "
                    f"{', '.join(model.budgets)} in its config's budgets)"
                )
            _check_budget(model.budgets[budget.name], f"model.budgets.{budget.name}", or_all=COUNTS_OR_ALL)
    dataset = cfg.get("dataset")
    if dataset is not None and dataset.get("scene") is not None:
        _check_scene(cfg)


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


def _check_budget(node: DictConfig | None, where: str, or_all: tuple[str, ...]) -> None:
    if not isinstance(node, DictConfig):
        return
    for key in node:
        if isinstance(node.get(key), DictConfig):
            _check_budget(node[key], f"{where}.{key}", or_all)
            continue
        value = node[key]
        if key in COUNTS:
            if value is None and key in or_all:
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                expected = "a positive integer" + (" or null (all)" if key in or_all else "")
                raise ContactbenchError(f"{where}.{key} is {value!r} (expected {expected})")
        elif key in RATES and (
            isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0)
        ):
            raise ContactbenchError(f"{where}.{key} is {value!r} (expected a positive number)")


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
