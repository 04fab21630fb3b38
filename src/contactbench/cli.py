"""Entry-point guard: user errors become one clear line and exit status 2; a failed multirun job lets the sweep go
on; the console carries no third-party advice that is not about this run."""

from __future__ import annotations

import difflib
import functools
import logging
import os
import sys
import warnings
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

from contactbench import atomic, settings
from contactbench.config import CONFIG_DIR
from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.folders import OUTCOME, FolderRefused

log = logging.getLogger("contactbench")


def _in_multirun() -> bool:
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


class CheckConfig(Callback):
    """Refuses an unset mandatory value (recordings=...) or an unknown +key before Hydra names the run folder."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        _exit_if_refused(config)

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        _exit_if_refused(config)


def _exit_if_refused(config: DictConfig) -> None:
    missing = settings.missing_keys(config)
    if missing:
        print(f"error: {missing[0]} is not set (expected {missing[0]}=... on the command line)", file=sys.stderr)
        sys.exit(2)
    unknown = settings.unknown_addition(config, settings.task_overrides(config))
    if unknown:
        print(f"error: {unknown}", file=sys.stderr)
        sys.exit(2)


def _one_line(error: OmegaConfBaseException) -> str:
    """OmegaConf's message and the key it was resolving, without its multi-line layout."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    key = next((line for line in lines if line.startswith("full_key:")), "")
    return f"config: {lines[0] if lines else type(error).__name__}" + (f" ({key})" if key else "")


def _record_outcome(status: str, why: str) -> None:
    """What the report says about a sweep job that wrote no metrics (done jobs need no record: metrics.json is it)."""
    folder = Path(HydraConfig.get().runtime.output_dir)
    folder.mkdir(parents=True, exist_ok=True)
    atomic.write_json(folder / OUTCOME, {"status": status, "why": why.removeprefix("error: ")})


class _NoAdvert(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(("💡 Tip", "`weights_only` was not set"))


NO_ADVERT = _NoAdvert()


def quiet_third_party() -> None:
    """Drop Lightning's litlogger advert on every fit, its note on every checkpoint saved with callback states (SysID
    saves one per generation), and its hint to use srun wherever Slurm is installed (a job under Slurm uses it; one
    started by hand on a Slurm login node is meant to run there). Once per process, however many jobs of a sweep it
    runs (addFilter and filterwarnings keep one copy of the same filter)."""
    logging.getLogger("pytorch_lightning.utilities.rank_zero").addFilter(NO_ADVERT)
    logging.getLogger("pytorch_lightning.trainer.connectors.checkpoint_connector").addFilter(NO_ADVERT)
    warnings.filterwarnings("ignore", message="The `srun` command is available on your system")


def check_command_line(task: str, argv: list[str] | None = None) -> None:
    """Hydra answers an override it cannot parse or a number given to a config group (budget=-1) with a traceback, and
    an option a group lacks (model=nosuch) or a key the config lacks (contxt_frames=3) with a page of text: each is
    one line here, naming the override and what was expected instead (exit 2). The config is composed as Hydra will
    compose it (0.2 s more, 0.5-0.7 s for a sweep); for a sweep, its first job and every option it names in a config
    group, so a misspelt option is refused before the first jobs have run."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra._internal.utils import create_config_search_path, get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import Glob
    from hydra.errors import HydraException, MissingConfigException, OverrideParseException

    arguments, _ = get_args_parser().parse_known_args(sys.argv[1:] if argv is None else argv)
    try:
        overrides = OverridesParser.create().parse_overrides(arguments.overrides)
    except OverrideParseException as error:
        _refuse(f"cannot parse an override: {str(error).splitlines()[0]}")
    for override in overrides:
        group = CONFIG_DIR / override.key_or_group
        if not group.is_dir() or override.is_delete() or isinstance(override.value(), Glob):
            continue
        values = list(override.sweep_iterator()) if override.is_sweep_override() else [override.value()]
        if not all(isinstance(value, (str, list)) for value in values):
            options = ", ".join(sorted(path.stem for path in group.glob("*.yaml")))
            _refuse(f"{override.input_line}: {override.key_or_group} is a config group (expected one of {options})")
    if arguments.shell_completion or arguments.config_name or arguments.config_dir:
        return  # another config than this entry point's: Hydra's to check
    composer = ConfigLoaderImpl(config_search_path=create_config_search_path(str(CONFIG_DIR)))
    try:
        mode = RunMode.MULTIRUN if arguments.multirun else RunMode.RUN
        cfg = composer.load_configuration(task, arguments.overrides, mode)
        if not arguments.multirun:
            return
        # The options a sweep may name include those hydra.searchpath=[...] adds (a model of one's own), placed as
        # Hydra places them: before the structured configs, which come last.
        search_path = create_config_search_path(str(CONFIG_DIR))
        schema = search_path.get_path().pop()
        for path in cfg.hydra.searchpath:
            search_path.append("command-line", path)
        search_path.append(schema.provider, schema.path)
        options_of = ConfigLoaderImpl(config_search_path=search_path)
        sweeps = OverridesParser.create(config_loader=options_of).parse_overrides(arguments.overrides)
        for override in sweeps:
            if override.is_sweep_override() and options_of.repository.group_exists(override.key_or_group):
                options = options_of.get_group_options(override.key_or_group)
                for value in override.sweep_string_iterator():
                    if value not in options:
                        _refuse(_no_option(override.key_or_group, value, options))
        composer.load_configuration(task, BasicSweeper.split_arguments(sweeps, None)[0][0], RunMode.RUN)
    except MissingConfigException as error:
        group, _, value = (error.missing_cfg_file or "").rpartition("/")
        _refuse(_no_option(group, value, error.options) if group and error.options else _joined(error))
    except (HydraException, OmegaConfBaseException) as error:
        _refuse(_no_key(error, overrides) or _joined(error))


def _no_option(group: str, value: str, options) -> str:
    close = difflib.get_close_matches(value, options, n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    return f"{group}={value}: {group} has no option {value} ({hint}expected one of {', '.join(options)})"


def _no_key(error: Exception, overrides) -> str | None:
    """Overriding a key the config lacks (contxt_frames=3): the override, the key, and the nearest key there is."""
    cause = error.__cause__
    if not isinstance(cause, (ConfigAttributeError, ConfigKeyError)) or not str(error).startswith("Could not override"):
        return None
    line = next(
        (o.input_line for o in overrides if str(error).startswith(f"Could not override '{o.key_or_group}'")), ""
    )
    parent = cause.full_key.rpartition(".")[0] if cause.full_key else ""
    siblings = [str(key) for key in cause.parent_node.keys()] if isinstance(cause.parent_node, DictConfig) else []
    close = difflib.get_close_matches(str(cause.key), siblings, n=1)
    hint = f"did you mean {parent + '.' if parent else ''}{close[0]}=...? " if close else ""
    return f"{line}: the config has no {cause.full_key} to override ({hint}a new key is added as +{line})"


def _joined(error: Exception) -> str:
    """Hydra's message, and the OmegaConf error under it, on one line."""
    parts = [str(error), str(error.__cause__) if isinstance(error.__cause__, OmegaConfBaseException) else ""]
    lines = [line.strip() for part in parts for line in part.splitlines() if line.strip()]
    return "; ".join(line for line in lines if not line.startswith(("full_key:", "object_type=")))


def _refuse(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def guarded(main):
    @functools.wraps(main)
    def wrapper(cfg):
        quiet_third_party()
        try:
            return main(cfg)
        except (ContactbenchError, FileNotFoundError, OmegaConfBaseException) as error:
            if os.environ.get("CONTACTBENCH_TRACEBACK"):
                raise
            message = f"error: {_one_line(error) if isinstance(error, OmegaConfBaseException) else error}"
            if _in_multirun():
                # One bad job (e.g. the hybrid model on a multi-body variant) must not stop the sweep. A refused
                # folder is another run's: its log file is not written either.
                if isinstance(error, FolderRefused):
                    print(f"{message} (job skipped)", file=sys.stderr)
                else:
                    log.error("%s (job skipped)", message)
                    _record_outcome("skipped" if isinstance(error, NotApplicable) else "failed", message)
                return None
            print(message, file=sys.stderr)
            sys.exit(2)

    return wrapper
