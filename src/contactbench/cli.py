"""Entry-point guard: user errors become one clear line and exit status 2; a failed multirun job lets the sweep go
on; the console carries no third-party advice that is not about this run."""

from __future__ import annotations

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
from omegaconf.errors import OmegaConfBaseException

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


def check_command_line(argv: list[str] | None = None) -> None:
    """Hydra answers an override it cannot parse, or a number given to a config group (budget=-1), with a
    traceback: one line naming the override and what was expected instead (exit 2). The rest is Hydra's to check."""
    from hydra._internal.utils import get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import Glob
    from hydra.errors import OverrideParseException

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
