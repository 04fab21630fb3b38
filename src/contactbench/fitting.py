"""Fit the configured model on a run's train and val splits, as its YAML says (models/base.py is the contract): an
analytical model's `fit`, or a Lightning module trained once, or once per setting of its `choose_on_val` grid,
keeping the setting whose best checkpoint scores lowest on val. What was selected goes to the run folder's
fitted.json, from which evaluate.py rebuilds the model (restore.py)."""

from __future__ import annotations

import itertools
import json
import logging
import math
from pathlib import Path

import pytorch_lightning as pl
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from contactbench import atomic, folders, restore, tracking
from contactbench.errors import ContactbenchError
from contactbench.models.base import ContactModel, ContactModule, require_contract
from contactbench.models.gnn import cpu_kernels
from contactbench.models.progress import FitProgress, Setting
from contactbench.recordings import Recordings

log = logging.getLogger(__name__)

# The same CPU kernels on every machine, for every torch model (models/gnn/cpu_kernels.py; importing it pinned them
# already): runs.py imports this module before any tensor is made, in train.py and evaluate.py alike.
CPU_KERNELS = cpu_kernels.pin()


def fit(cfg: DictConfig, dataset: Recordings, output_dir: Path, logger) -> ContactModel:
    """The fitted model, its record written to output_dir/fitted.json."""
    kind = cfg.model.kind
    if kind == "analytical":
        return fit_analytical(cfg, dataset, output_dir)
    if kind == "lightning":
        return fit_lightning(cfg, dataset, output_dir, logger)
    raise ContactbenchError(f"model.kind must be 'analytical' or 'lightning', got {kind!r}")


def fit_analytical(cfg: DictConfig, dataset: Recordings, output_dir: Path) -> ContactModel:
    model = instantiate(cfg.model.contact_model)
    require_contract(model, ContactModel, "model.contact_model")
    model.fit(dataset)
    state = model.fitted_state()
    folders.check_fitted_state(state, output_dir / "fitted.json", f"{cfg.model.name}.fitted_state()")
    atomic.write_json(output_dir / "fitted.json", {"model": cfg.model.name, "state": state})
    return model


def fit_lightning(cfg: DictConfig, dataset: Recordings, output_dir: Path, logger) -> ContactModel:
    """One fit, or one per setting of the model's `choose_on_val` grid, keeping the setting whose best checkpoint has
    the lowest val/pos_err: the same choice for a named dataset and a user's own folder. With `choose_at_step`, every
    setting trains to that step only, and the one best on val so far goes on to the end (choose_settings)."""
    candidates = settings_grid(cfg.model.get("choose_on_val"))
    if not candidates:
        checkpoint, _ = fit_one(cfg, cfg.model, dataset, output_dir, None, logger)
        chosen: dict = {}
    else:
        scores = choose_settings(cfg, candidates, dataset, output_dir, logger)
        winner = min(scores, key=_score)
        checkpoint, chosen = winner["checkpoint"], {"chosen_on_val": winner["setting"], "candidates": scores}
        if cfg.model.get("choose_at_step"):
            chosen["chosen_at_step"] = int(cfg.model.choose_at_step)
        tracking.log_choice(logger, winner["setting"])
    module = restore.load_module(cfg, dataset, output_dir / "checkpoints" / checkpoint)
    atomic.write_json(
        output_dir / "fitted.json",
        {
            "model": cfg.model.name,
            "checkpoint": checkpoint,
            **chosen,
            **module.fitted_summary(),
            "cpu_kernels": cpu_kernels.in_effect(),
        },
    )
    return module.to_contact_model()


def choose_settings(
    cfg: DictConfig, candidates: list[dict], dataset: Recordings, output_dir: Path, logger
) -> list[dict]:
    """Each setting fitted from the same starting weights, with its best val/pos_err (null where it has none) and best
    checkpoint. With model.choose_at_step = D, each is fitted to step D only (its learning rate still decaying over
    max_steps), and the one with the lowest val/pos_err so far is then resumed to max_steps: settings x D +
    (max_steps - D) steps instead of settings x max_steps. The others keep their score at D, which
    checkpoints/chosen_at_step.json records once they are all there, so that a run killed afterwards resumes the same
    choice. The leader ends bit for bit as its uninterrupted fit would have."""
    stop_at = cfg.model.get("choose_at_step")
    record = output_dir / "checkpoints" / "chosen_at_step.json"
    fitted = read_choice(record, stop_at, candidates) if stop_at and cfg.resume and record.exists() else None
    if fitted is None:
        fitted = []
        for k, setting in enumerate(candidates, start=1):
            name = setting_name(setting)
            at = (k, len(candidates), name)
            best, score = fit_one(
                cfg, _with(cfg.model, setting), dataset, output_dir, at, tracking.prefixed(logger, name), stop_at
            )
            log.info("%s: best val/pos_err %.4f%s", name, score, f" at step {stop_at}" if stop_at else "")
            fitted.append({"setting": setting, "val_pos_err": _finite(score), "checkpoint": f"{name}/{best}"})
        if stop_at:
            atomic.write_json(record, {"chosen_at_step": int(stop_at), "candidates": fitted})
    if not stop_at:
        return fitted
    k, leader = min(enumerate(fitted, start=1), key=lambda item: _score(item[1]))
    name = setting_name(leader["setting"])
    log.info("%s leads at step %d: on to the end", name, stop_at)
    at = (k, len(candidates), name)
    best, score = fit_one(
        cfg, _with(cfg.model, leader["setting"]), dataset, output_dir, at, tracking.prefixed(logger, name), resume=True
    )
    final = {**leader, "val_pos_err": _finite(score), "checkpoint": f"{name}/{best}"}
    return [final if entry is leader else entry for entry in fitted]


def _finite(score: float) -> float | None:
    return score if math.isfinite(score) else None  # JSON has no NaN: a fit without a val score records null


def _score(entry: dict) -> float:
    return math.inf if entry["val_pos_err"] is None else entry["val_pos_err"]


def read_choice(path: Path, step: int, candidates: list[dict]) -> list[dict]:
    """The settings' scores at `step` that choose_settings recorded in a run folder; one line naming the file and
    the field where it is not what this fit would have written (a run folder is a user's file)."""
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ContactbenchError(f"{path}: cannot be read as JSON ({error})") from None
    entries = record.get("candidates") if isinstance(record, dict) else None
    if not isinstance(record, dict) or record.get("chosen_at_step") != int(step):
        raise ContactbenchError(f"{path}: field 'chosen_at_step' must be {int(step)}, this fit's model.choose_at_step")
    if not isinstance(entries, list) or [e.get("setting") if isinstance(e, dict) else None for e in entries] != [
        dict(setting) for setting in candidates
    ]:
        raise ContactbenchError(f"{path}: field 'candidates' must list this fit's settings in order: {candidates}")
    for entry in entries:
        name, score = setting_name(entry["setting"]), entry.get("val_pos_err")
        if entry.get("checkpoint") not in (f"{name}/best.ckpt", f"{name}/last.ckpt"):
            raise ContactbenchError(
                f"{path}: field 'checkpoint' must be {name}/best.ckpt, got {entry.get('checkpoint')!r}"
            )
        if score is not None and (isinstance(score, bool) or not isinstance(score, (int, float))):
            raise ContactbenchError(f"{path}: field 'val_pos_err' must be a number or null, got {score!r}")
    return entries


def _with(model_cfg: DictConfig, setting: dict) -> DictConfig:
    """The model's config with one setting of its grid."""
    copied = model_cfg.copy()
    for key, value in setting.items():
        OmegaConf.update(copied, key, value, merge=False)
    return copied


def settings_grid(grid: DictConfig | None) -> list[dict]:
    """Every combination of a `choose_on_val` tree under model ({module: {noise_std: [values]}}), as {dotted key:
    value} settings (none: [])."""
    if not grid:
        return []
    leaves = tracking.flatten(OmegaConf.to_container(grid))
    keys = list(leaves)
    return [dict(zip(keys, values)) for values in itertools.product(*(list(leaves[key]) for key in keys))]


def setting_name(setting: dict) -> str:
    """A setting's checkpoint folder and label: its leaf keys and values ('noise_std=0.0002')."""
    return ",".join(f"{key.rsplit('.', 1)[-1]}={value:g}" for key, value in setting.items())


def fit_one(
    cfg: DictConfig,
    model_cfg: DictConfig,
    dataset: Recordings,
    output_dir: Path,
    setting: Setting | None,
    logger,
    stop_at: int | None = None,
    resume: bool = False,
) -> tuple[str, float]:
    """Fit model_cfg's Lightning module, checkpoints in output_dir/checkpoints/<setting name> (resumed from its
    last.ckpt when cfg.resume or `resume`), to max_steps or, with `stop_at`, to that step (a fit already there does
    not train). Returns the selected checkpoint's file name and its val/pos_err (NaN without one)."""
    name = setting[2] if setting else ""
    checkpoint_dir = output_dir / "checkpoints" / name
    pl.seed_everything(cfg.seed, workers=True)  # every setting starts from the weights a fit of it alone starts from
    # Objects (the dataset) go to the partial, not through instantiate's config merge.
    datamodule = instantiate(model_cfg.datamodule, _partial_=True)(dataset=dataset, context_frames=cfg.context_frames)
    module = instantiate(model_cfg.module, _partial_=True)(dataset=dataset, context_frames=cfg.context_frames)
    require_contract(module, ContactModule, "model.module")
    trainer = make_trainer(cfg, model_cfg, checkpoint_dir, output_dir, logger, setting, stop_at)
    last = checkpoint_dir / "last.ckpt"
    resume_from = str(last) if (cfg.resume or resume) and last.exists() else None
    if resume_from:
        log.info("resuming from %s", resume_from)  # folders.check has checked its signature and contents
        step = int(torch.load(resume_from, weights_only=True, map_location="cpu")["global_step"])
        tracking.drop_rows_from_step(output_dir, step, prefix=f"{name}/" if name else "")
    trainer.fit(module, datamodule=datamodule, ckpt_path=resume_from, weights_only=True)
    callback = trainer.checkpoint_callback
    best_path = callback.best_model_path if callback else ""
    score = callback.best_model_score if callback is not None else None
    return (Path(best_path).name if best_path else "last.ckpt"), (math.nan if score is None else float(score))


class StopAtStep(pl.Callback):
    """Ends a fit once it has trained `step` steps, after that step's validation, without changing its schedule (the
    learning rate still decays over max_steps, so that the fit resumed later goes on as if never stopped); a fit
    resumed at or past `step` does not train."""

    def __init__(self, step: int):
        self.step = int(step)

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        trainer.should_stop = trainer.global_step >= self.step

    def on_train_batch_end(self, trainer: pl.Trainer, *args) -> None:
        trainer.should_stop = trainer.should_stop or trainer.global_step >= self.step


def make_trainer(
    cfg: DictConfig,
    model_cfg: DictConfig,
    checkpoint_dir: Path,
    output_dir: Path,
    logger,
    setting: Setting | None,
    stop_at: int | None = None,
) -> pl.Trainer:
    """cfg.trainer with the model's own trainer settings and callbacks; the progress callback is told the setting."""
    callbacks = make_callbacks(model_cfg, checkpoint_dir) + ([StopAtStep(stop_at)] if stop_at else [])
    for callback in callbacks:
        if isinstance(callback, FitProgress):
            callback.setting = setting
    return instantiate(
        cfg.trainer,
        **model_cfg.get("trainer", {}),
        callbacks=callbacks,
        logger=logger if logger is not None else False,
        default_root_dir=str(output_dir),
    )


def make_callbacks(model_cfg: DictConfig, checkpoint_dir: Path) -> list[pl.Callback]:
    """The model's configured callbacks; checkpoints go into the run folder, where a restarted run looks for them."""
    nodes = (model_cfg.get("callbacks") or {}).values()
    return [
        instantiate(node, **({"dirpath": str(checkpoint_dir)} if node._target_.endswith("ModelCheckpoint") else {}))
        for node in nodes
    ]
