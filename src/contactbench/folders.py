"""A run folder's own record: decide whether a command may use a folder before it writes anything, then record it."""

from __future__ import annotations

import hashlib
import json
import re
import warnings
from pathlib import Path

import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_object
from omegaconf import DictConfig, OmegaConf

from contactbench import atomic
from contactbench.errors import ContactbenchError

SIGNATURE = "signature.json"
SCORED = "scored.json"  # in an evaluate folder: what its scores are of (a signature, as a train folder's)
INDEX = "index"  # under paths.log_dir: one entry per fitted run, named by its signature
OUTCOME = "outcome.json"  # in a sweep job's folder that wrote no metrics: skipped or failed, and why


class FolderRefused(ContactbenchError):
    """A command refused to use a run folder; the folder was left exactly as it was."""


def run_signature(cfg: DictConfig) -> dict:
    """What makes a fitted model what it is; a run folder only resumes or serves a model with the same signature."""
    model = OmegaConf.to_container(cfg.model, resolve=True)
    model.pop("budgets", None)  # the budget in use is resolved into the model's fields; the others do not matter
    signature = {
        "model": model,
        # A user's recordings are what their files hold (the variant is their content's key), wherever they lie.
        "dataset": f"recordings {cfg.dataset.variant}" if cfg.dataset.name == "recordings" else str(cfg.dataset.path),
        "context_frames": int(cfg.context_frames),
        "seed": int(cfg.seed),
    }
    observation = cfg.get("observation")
    if observation is not None and (observation.noise_mm != 0 or observation.frame_stride != 1):
        # Only when the data are observed otherwise: the folders of plain runs keep their signature.
        signature["observation"] = OmegaConf.to_container(observation, resolve=True)
    return signature


# What a refused command can do instead: train.py writes wherever hydra.run.dir says; evaluate.py writes wherever
# hydra.run.dir says too, but scores the run that train_dir names.
ADVICE = {
    "resume": "Train in another folder with hydra.run.dir=FOLDER, or replace that run with resume=false",
    "score the model of": "Name the train run of these settings with train_dir=FOLDER",
    "rewrite": "Score into another folder with hydra.run.dir=FOLDER, or replace those scores with overwrite=true",
}


def same_signature(cfg: DictConfig, run_dir: Path) -> bool:
    """Whether run_dir holds no signature, or this command's."""
    recorded = Path(run_dir) / SIGNATURE
    return not recorded.is_file() or _read_signature(recorded) == json.loads(json.dumps(run_signature(cfg)))


def check_signature(cfg: DictConfig, run_dir: Path, action: str) -> None:
    recorded = Path(run_dir) / SIGNATURE
    if same_signature(cfg, run_dir):
        return
    _refuse_other(recorded, run_signature(cfg), "the run there was made", action)


def scored_signature(cfg: DictConfig, train_dir: Path | None) -> dict:
    """What an evaluate folder's scores are of: the run's signature, the split, and the train run whose model was
    scored (None: a model with nothing fitted). The folder's name says only some of it (not context_frames, a model
    field set on the command line, nor train_dir)."""
    return {
        **run_signature(cfg),
        "split": str(cfg.split),
        "train_dir": None if train_dir is None else str(Path(train_dir).resolve()),
    }


def _refuse_other(recorded: Path, wanted: dict, what: str, action: str) -> None:
    """Refuse (FolderRefused) where `recorded` holds another signature than `wanted`, naming what differs."""
    wanted = json.loads(json.dumps(wanted))
    if not recorded.is_file() or _read_signature(recorded) == wanted:
        return
    differences = signature_differences(_read_signature(recorded), wanted)
    shown = "; ".join(differences[:3]) + (f"; and {len(differences) - 3} more" if len(differences) > 3 else "")
    raise FolderRefused(
        f"{recorded}: {what} with other settings than this command ({shown}); cannot {action} it. "
        + ADVICE.get(action, "Use another folder")
    )


def signature_differences(recorded: object, wanted: dict) -> list[str]:
    """'key: value there, value here' for every setting two signatures differ in, by the config key a user would
    override (a budget by the model fields it sets)."""
    there, here = _flat(recorded), _flat(wanted)
    keys = [key for key in sorted(set(there) | set(here)) if there.get(key, _UNSET) != here.get(key, _UNSET)]
    if "model.name" in keys:  # another model: its name says it, not every field the two configs do not share
        keys = [key for key in keys if key == "model.name" or not key.startswith("model.")]
    return [f"{key}: {_shown(there, key)} there, {_shown(here, key)} here" for key in keys]


_UNSET = object()


def _flat(tree: object, prefix: str = "") -> dict:
    if isinstance(tree, dict) and (tree or not prefix):
        return {key: value for name, item in tree.items() for key, value in _flat(item, f"{prefix}{name}.").items()}
    return {prefix[:-1] or "signature": tree}


def _shown(values: dict, key: str) -> str:
    return "unset" if key not in values else _clip(json.dumps(values[key]), 60)


def _read_signature(path: Path) -> object:
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise FolderRefused(
            f"{path}: not valid JSON ({error}); expected the signature contactbench wrote for that run"
        ) from None


def claim(cfg: DictConfig, output_dir: Path, task: str) -> None:
    """Refuse (FolderRefused, nothing written) or take the folder: `check` then `record`."""
    check(cfg, output_dir, task)
    record(cfg, output_dir, task)


def check(cfg: DictConfig, output_dir: Path, task: str, scored: dict | None = None) -> None:
    """Refuse (FolderRefused) a folder this command may not use; writes nothing. `scored`: what evaluate's scores
    will be of (`scored_signature`): scores of other settings there are not rewritten unless cfg.overwrite."""
    output_dir = Path(output_dir)
    if task == "train":
        if cfg.get("resume", True):
            check_signature(cfg, output_dir, "resume")
            check_checkpoint(cfg, output_dir)
    elif (output_dir / SIGNATURE).is_file():
        raise FolderRefused(
            f"{output_dir / SIGNATURE}: this folder holds a train run; {task} would write into it "
            "(expected a folder of its own: leave hydra.run.dir at its default or name a new folder)"
        )
    elif scored is not None and not cfg.get("overwrite", False):
        _refuse_other(output_dir / SCORED, scored, "the scores there were made", "rewrite")


def release(output_dir: Path) -> None:
    """Undo a train run's claim on its folder when it failed before leaving anything to resume (no checkpoint, no
    fitted.json): its signature would otherwise refuse the next command, e.g. the same run with its YAML fixed."""
    output_dir = Path(output_dir)
    if not any((output_dir / "checkpoints").rglob("*.ckpt")) and not (output_dir / "fitted.json").exists():
        (output_dir / SIGNATURE).unlink(missing_ok=True)


def record(cfg: DictConfig, output_dir: Path, task: str) -> None:
    """Take a checked folder: train records its signature, every task its config.

    Hydra's own copy of the config is switched off (conf/hydra/default.yaml: output_subdir: null) because Hydra
    writes it when the job starts, before any check could refuse; the same files are written here, afterwards.
    """
    output_dir = Path(output_dir)
    if task == "train":
        atomic.write_json(output_dir / SIGNATURE, run_signature(cfg))
    _write_hydra_record(cfg, output_dir)


def record_scores(output_dir: Path, scored: dict) -> None:
    """What the scores just written to output_dir are of (`scored_signature`): written with them, so that a command
    refused or failed on the way leaves the record of the scores that are there."""
    atomic.write_json(Path(output_dir) / SCORED, scored)


def check_checkpoint(cfg: DictConfig, output_dir: Path) -> None:
    """A checkpoint to resume from loads as plain tensors and numbers (never unpickling code), with valid callback
    states."""
    if cfg.model.get("kind") != "lightning":
        return
    for path in sorted((Path(output_dir) / "checkpoints").rglob("last.ckpt")):  # one per setting chosen on val
        _check_one_checkpoint(cfg, path)


def _check_one_checkpoint(cfg: DictConfig, path: Path) -> None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch warns about pickle protocols before refusing; one line is enough
            checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - whatever the bytes are, the answer is the same refusal
        raise FolderRefused(
            f"{path}: not a checkpoint contactbench can resume ({_short(error)}); expected plain tensors and numbers. "
            "resume=false starts over"
        ) from None
    if not isinstance(checkpoint, dict):
        raise FolderRefused(f"{path}: holds a {type(checkpoint).__name__} (expected a Lightning checkpoint dict)")
    states = checkpoint.get("callbacks") or {}
    for node in (cfg.model.get("callbacks") or {}).values():
        callback = get_object(node._target_)
        if not isinstance(callback, type) or not hasattr(callback, "check_state"):
            continue  # a factory (a progress reporter) or a class that keeps no state worth checking
        key = callback.__qualname__
        if key not in states:
            raise FolderRefused(
                f"{path}: field 'callbacks.{key}' is missing (expected the state of the {key} callback)"
            )
        try:
            callback.check_state(states[key], f"{path}: callbacks.{key}")
        except ContactbenchError as error:
            raise FolderRefused(str(error)) from None


def _short(error: Exception) -> str:
    """torch's weights-only refusal is a page of advice; the line that says what was refused is enough here."""
    text = str(error)
    match = re.search(r"WeightsUnpickler error:\s*(.+?)(?:\n\n|$)", text, flags=re.S)
    detail = match.group(1) if match else (text.strip().splitlines() or [""])[0]
    return f"{type(error).__name__}: {' '.join(detail.split())}"


def _write_hydra_record(cfg: DictConfig, output_dir: Path) -> None:
    """The .hydra/ files Hydra would have written (the report rebuilds models from .hydra/config.yaml)."""
    if not HydraConfig.initialized():
        return  # composed in a test or a library call: no Hydra job, nothing of Hydra's to record
    hydra_cfg = HydraConfig.instance().cfg
    if hydra_cfg.hydra.output_subdir is not None:
        return  # Hydra wrote its own copy (a user re-enabled it)
    record = output_dir / ".hydra"
    atomic.write_text(record / "config.yaml", OmegaConf.to_yaml(cfg))
    atomic.write_text(record / "hydra.yaml", OmegaConf.to_yaml(hydra_cfg))
    atomic.write_text(record / "overrides.yaml", OmegaConf.to_yaml(hydra_cfg.hydra.overrides.task))


def check_fitted_state(state: object, path: Path, field: str) -> None:
    """A fitted state is a dict of finite numbers, strings, booleans and lists of them (nested): JSON, never code."""

    def plain(value: object) -> bool:
        if isinstance(value, bool | str) or value is None:
            return True
        if isinstance(value, int | float):
            return bool(np.isfinite(value))
        if isinstance(value, list | tuple):
            return all(plain(item) for item in value)
        if isinstance(value, dict):
            return all(isinstance(key, str) and plain(item) for key, item in value.items())
        return False

    if not isinstance(state, dict) or not plain(state):
        raise FolderRefused(
            f"{path}: field '{field}' is not plain JSON data (expected a dict of finite numbers, strings, booleans and "
            f"lists of them; got {type(state).__name__} {_clip(repr(state))})"
        )


def read_fitted_state(path: Path) -> dict:
    """The `state` an analytical model's train run wrote to fitted.json, checked before the model sees it."""
    try:
        document = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise FolderRefused(f"{path}: not valid JSON ({error}); expected the fitted.json train.py wrote") from None
    if not isinstance(document, dict) or "state" not in document:
        raise FolderRefused(f"{path}: field 'state' is missing (expected the fitted state train.py wrote)")
    check_fitted_state(document["state"], path, "state")
    return document["state"]


def _clip(text: str, limit: int = 80) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def signature_key(cfg: DictConfig) -> str:
    """A short, stable name for a run signature: the run index's file name."""
    text = json.dumps(json.loads(json.dumps(run_signature(cfg))), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def index_run(cfg: DictConfig, output_dir: Path) -> None:
    """Record where the model of this signature was fitted (paths.log_dir/index/<key>.json): evaluate.py finds runs
    made by any sweep or folder name through it."""
    entry = {"run": str(Path(output_dir).resolve()), "model": cfg.model.name, "dataset": str(cfg.dataset.path)}
    atomic.write_json(Path(cfg.paths.log_dir) / INDEX / f"{signature_key(cfg)}.json", entry)


def indexed_run(cfg: DictConfig) -> Path | None:
    """The run folder the index holds for this signature, if any (its signature is checked again when loaded)."""
    path = Path(cfg.paths.log_dir) / INDEX / f"{signature_key(cfg)}.json"
    if not path.is_file():
        return None
    try:
        run = json.loads(path.read_text())["run"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as error:
        raise FolderRefused(
            f"{path}: field 'run' unreadable ({error!r}); expected the index entry train.py wrote"
        ) from None
    if not isinstance(run, str):
        raise FolderRefused(f"{path}: field 'run' is a {type(run).__name__} (expected a folder path)")
    return Path(run)
