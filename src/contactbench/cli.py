"""Entry-point guard: user errors become one clear line and exit status 2; a failed multirun job lets the sweep go
on; the console carries no third-party advice that is not about this run."""

from __future__ import annotations

import difflib
import functools
import logging
import os
import re
import signal
import sys
import warnings
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

from contactbench import atomic, helptext  # helptext: the resolvers conf/hydra/help/ lists options with
from contactbench.config import CONFIG_DIR
from contactbench.errors import ContactbenchError, NotApplicable

log = logging.getLogger("contactbench")


def _in_multirun() -> bool:
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def _one_line(error: OmegaConfBaseException) -> str:
    """OmegaConf's message and the key it was resolving, without its multi-line layout."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    key = next((line for line in lines if line.startswith("full_key:")), "")
    return f"config: {lines[0] if lines else type(error).__name__}" + (f" ({key})" if key else "")


def _record_outcome(status: str, why: str) -> None:
    """What the report says about a sweep job that wrote no metrics (done jobs need no record: metrics.json is it)."""
    from contactbench.folders import OUTCOME  # imports torch: not before --help has answered

    folder = Path(HydraConfig.get().runtime.output_dir)
    folder.mkdir(parents=True, exist_ok=True)
    atomic.write_json(folder / OUTCOME, {"status": status, "why": why.removeprefix("error: ")})


class _Drop(logging.Filter):
    """Drops the records whose message starts with one of `starts`."""

    def __init__(self, *starts: str):
        super().__init__()
        self.starts = starts

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(self.starts)


NO_ADVERT = _Drop("💡 Tip", "`weights_only` was not set")
# Lightning's report of what it found and did, true of every run here and about none in particular: the seed (set
# again before every fit), accelerators (trainer=gpu says which is used), and a fit ending at the step limit it was
# given.
NO_ROUTINE = _Drop(
    "GPU available:",
    "TPU available:",
    "HPU available:",
    "`Trainer.fit` stopped: `max_steps=",
    "`Trainer.fit` stopped: `max_epochs=",
)
NO_SEED = _Drop("Seed set to")


def quiet_third_party() -> None:
    """Drop Lightning's litlogger advert on every fit, its note on every checkpoint saved with callback states (SysID
    saves one per generation), its hint to use srun wherever Slurm is installed (a job under Slurm uses it; one
    started by hand on a Slurm login node is meant to run there), its routine reports (NO_ROUTINE, NO_SEED), and the
    deprecation its own pytree helper triggers in torch (Lightning's to fix, not the user's). Each by its message
    alone: anything else Lightning says still shows. Once per process, however many jobs of a sweep it runs
    (addFilter and filterwarnings keep one copy of the same filter)."""
    logging.getLogger("pytorch_lightning.utilities.rank_zero").addFilter(NO_ADVERT)
    logging.getLogger("pytorch_lightning.utilities.rank_zero").addFilter(NO_ROUTINE)
    logging.getLogger("lightning_fabric.utilities.seed").addFilter(NO_SEED)
    logging.getLogger("pytorch_lightning.trainer.connectors.checkpoint_connector").addFilter(NO_ADVERT)
    warnings.filterwarnings("ignore", message="The `srun` command is available on your system")
    warnings.filterwarnings("ignore", r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning)


def check_command_line(task: str, argv: list[str] | None = None) -> None:
    """Hydra answers an override it cannot parse or a number given to a config group (budget=-1) with a traceback, and
    an option a group lacks (model=nosuch) or a key the config lacks (contxt_frames=3) with a page of text: each is one
    line here, naming the override and what was expected instead (exit 2). The config is composed as Hydra will compose
    it (a fraction of a second more, a little more for a sweep); for a sweep, its first job and every option it names in
    a config group, so a misspelt option is refused before the first jobs have run."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra._internal.utils import create_config_search_path, get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import Glob
    from hydra.errors import HydraException, MissingConfigException, OverrideParseException

    words = sys.argv[1:] if argv is None else argv
    arguments, unknown = get_args_parser().parse_known_args(words)
    if argv is None and (arguments.help or arguments.hydra_help or arguments.cfg or arguments.info):
        # what is printed and nothing run: `--help | head` ends quietly at a closed pipe, as other commands do
        signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    unwritten = _not_key_value(task, words, arguments.overrides, unknown)
    if unwritten:
        _refuse(unwritten)
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
        _refuse(_no_group(task, error, overrides) or _no_key(error, overrides) or _joined(error))


# Which group a lone option names (`sysid` is model=sysid; contactnets_cube is a dataset before it is a variant).
GROUP_ORDER = ("model", "dataset", "budget", "variant", "logger", "trainer", "experiment")
EXAMPLE = {"train": "model=sysid", "evaluate": "model=sysid", "generate": "variant=frictioncubes_0.5"}


def _not_key_value(task: str, words: list[str], overrides: list[str], unknown: list[str]) -> str | None:
    """A command line written as other tools take options (`--model sysid`, `dataset contactnets_cube`, a lone
    `sysid`), which Hydra answers with a parse error about the word alone: what to write instead, or None."""
    for flag in unknown:
        if flag.startswith("-") and flag.lstrip("-"):
            key, _, value = flag.lstrip("-").partition("=")
            after = words[words.index(flag) + 1 :][:1]
            if not value and after and "=" not in after[0] and not after[0].startswith("-"):
                return f"{flag} {after[0]}: write key=value, without dashes ({key}={after[0]})"
            return f"{flag}: write key=value, without dashes ({key}={value or '...'})"
    keys = _top_level_keys(task)
    for index, word in enumerate(overrides):
        if "=" in word or word.startswith("~"):  # ~key deletes a key: Hydra's own syntax without a value
            continue
        after = overrides[index + 1 : index + 2]
        if word in keys:
            if after and "=" not in after[0]:
                return f"{word} {after[0]}: write key=value ({word}={after[0]})"
            return f"{word}: write key=value ({word}=...)"
        groups = [*GROUP_ORDER, *sorted(path.name for path in CONFIG_DIR.iterdir() if path.is_dir())]
        group = next((group for group in groups if (CONFIG_DIR / group / f"{word}.yaml").is_file()), None)
        if group:
            return f"{word}: write key=value ({group}={word})"
        close = difflib.get_close_matches(word, sorted(keys), n=1)
        example = f"{close[0]}=..." if close else EXAMPLE.get(task, f"recordings={word}")
        return f"{word}: write key=value (e.g. {example})"
    return None


def _top_level_keys(task: str) -> set[str]:
    """What a command line may set without a dot: the config groups, the entry point's own keys and the datasets'."""
    groups = {path.name for path in CONFIG_DIR.iterdir() if path.is_dir()}
    entry = OmegaConf.load(CONFIG_DIR / f"{task}.yaml")
    own = {str(key) for key in entry if key != "defaults"}
    for item in OmegaConf.to_container(entry, resolve=False).get("defaults", []):
        # a group option of the entry's own that sets top-level keys (conf/protocol/: # @package _global_)
        for group, option in item.items() if isinstance(item, dict) else []:
            path = CONFIG_DIR / str(group) / f"{option}.yaml"
            if path.is_file() and path.read_text().startswith("# @package _global_"):
                own |= {str(key) for key in OmegaConf.load(path) if key != "defaults"}
    return groups | own | {key for keys in helptext.dataset_settings().values() for key in keys}


def _no_option(group: str, value: str, options) -> str:
    close = difflib.get_close_matches(value, options, n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    return f"{group}={value}: {group} has no option {value} ({hint}expected one of {', '.join(options)})"


def _no_group(task: str, error: Exception, overrides) -> str | None:
    """A config group this entry point does not use (diagnose.py model=sysid), which Hydra would have appended with
    +group=...: said so, with what the entry point takes instead."""
    found = re.match(r"Could not override '([^']+)'\. No match in the defaults list", str(error))
    if not found:
        return None
    group = found.group(1)
    line = next((o.input_line for o in overrides if o.key_or_group == group), group)
    if task == "diagnose" and group == "dataset":
        return (
            f"{line}: diagnose.py reads a recordings folder, not a dataset (write recordings=<folder>, e.g. "
            "recordings=assets/contactnets_cube)"
        )
    return f"{line}: {task}.py takes no {group} (python {task}.py --help lists what it takes)"


def _no_key(error: Exception, overrides) -> str | None:
    """Overriding a key the config lacks (contxt_frames=3): the override, the key, and the nearest key there is."""
    cause = error.__cause__
    if not isinstance(cause, (ConfigAttributeError, ConfigKeyError)) or not str(error).startswith("Could not override"):
        return None
    line = next(
        (o.input_line for o in overrides if str(error).startswith(f"Could not override '{o.key_or_group}'")), ""
    )
    parent = cause.full_key.rpartition(".")[0] if cause.full_key else ""
    owners = [name for name, keys in helptext.dataset_settings().items() if not parent and cause.key in keys]
    if owners:  # friction=0.3 with dataset=bouncycubes, recordings=... without dataset=recordings
        either = " or ".join(f"dataset={owner}" for owner in owners)
        return f"{line}: {cause.key} is a setting of {either} (write dataset={owners[0]} {line})"
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


def _not_built(error: InstantiationException) -> str:
    """A `_target_` Hydra could not import or call, on one line: which config node, which target, and what to do."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    node = next((line.removeprefix("full_key:").strip() for line in lines if line.startswith("full_key:")), "")
    where = f"{node}: " if node else ""
    located = re.match(r"Error locating target '([^']+)'", lines[0] if lines else "")
    if located:
        target, package = located.group(1), located.group(1).split(".")[0]
        cause = _innermost(error)
        if isinstance(cause, ModuleNotFoundError) and (cause.name or package).split(".")[0] == package:
            return (
                f"{where}cannot import {target}: no module {cause.name or package} "
                f"(add the folder that holds {package}/ to PYTHONPATH)"
            )
        return f"{where}cannot import {target}: {_first_line(cause)}"
    called = re.match(r"Error in call to target '([^']+)'", lines[0] if lines else "")
    cause = error.__cause__
    if called and cause is not None:
        return f"{where}{called.group(1)}(...) raised {_first_line(cause)} (CONTACTBENCH_TRACEBACK=1 shows where)"
    return f"{where}{'; '.join(line for line in lines if not line.startswith('full_key:'))}"


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return f"{type(error).__name__}: {text.splitlines()[0]}" if text else type(error).__name__


def _innermost(error: BaseException) -> BaseException:
    while error.__cause__ is not None:
        error = error.__cause__
    return error


def guarded(main):
    @functools.wraps(main)
    def wrapper(cfg):
        quiet_third_party()
        try:
            return main(cfg)
        except (ContactbenchError, FileNotFoundError, OmegaConfBaseException, InstantiationException) as error:
            from contactbench.folders import FolderRefused  # imports torch: not before --help has answered

            if os.environ.get("CONTACTBENCH_TRACEBACK"):
                raise
            if isinstance(error, OmegaConfBaseException):
                message = f"error: {_one_line(error)}"
            elif isinstance(error, InstantiationException):
                message = f"error: {_not_built(error)}"
            else:
                message = f"error: {error}"
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
