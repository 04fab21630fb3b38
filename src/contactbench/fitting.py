"""Fit the configured model on a run's train and val splits, as its YAML says (models/base.py is the contract): an
analytical model's `fit`, or a Lightning module trained once, or once per setting of its `choose_on_val` grid,
keeping the setting whose best checkpoint scores lowest on val. What was selected goes to the run folder's
fitted.json, from which evaluate.py rebuilds the model (restore.py)."""

from __future__ import annotations

import itertools
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
    the lowest val/pos_err: the same choice for a named dataset and a user's own folder."""
    candidates = settings_grid(cfg.model.get("choose_on_val"))
    if not candidates:
        checkpoint, _ = fit_one(cfg, cfg.model, dataset, output_dir, None, logger)
        chosen: dict = {}
    else:
        scores = []
        for k, setting in enumerate(candidates, start=1):
            model_cfg = cfg.model.copy()
            for key, value in setting.items():
                OmegaConf.update(model_cfg, key, value, merge=False)
            name = setting_name(setting)
            at = (k, len(candidates), name)
            best, score = fit_one(cfg, model_cfg, dataset, output_dir, at, tracking.prefixed(logger, name))
            log.info("%s: best val/pos_err %.4f", name, score)
            scores.append({"setting": setting, "val_pos_err": score, "checkpoint": f"{name}/{best}"})
        winner = min(
            scores, key=lambda entry: entry["val_pos_err"] if math.isfinite(entry["val_pos_err"]) else math.inf
        )
        checkpoint, chosen = winner["checkpoint"], {"chosen_on_val": winner["setting"], "candidates": scores}
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
    cfg: DictConfig, model_cfg: DictConfig, dataset: Recordings, output_dir: Path, setting: Setting | None, logger
) -> tuple[str, float]:
    """Fit model_cfg's Lightning module, checkpoints in output_dir/checkpoints/<setting name> (resumed from its
    last.ckpt when cfg.resume). Returns the selected checkpoint's file name and its val/pos_err (NaN without one)."""
    name = setting[2] if setting else ""
    checkpoint_dir = output_dir / "checkpoints" / name
    pl.seed_everything(cfg.seed, workers=True)  # every setting starts from the weights a fit of it alone starts from
    # Objects (the dataset) go to the partial, not through instantiate's config merge.
    datamodule = instantiate(model_cfg.datamodule, _partial_=True)(dataset=dataset, context_frames=cfg.context_frames)
    module = instantiate(model_cfg.module, _partial_=True)(dataset=dataset, context_frames=cfg.context_frames)
    require_contract(module, ContactModule, "model.module")
    trainer = make_trainer(cfg, model_cfg, checkpoint_dir, output_dir, logger, setting)
    last = checkpoint_dir / "last.ckpt"
    resume_from = str(last) if cfg.resume and last.exists() else None
    if resume_from:
        log.info("resuming from %s", resume_from)  # folders.check has checked its signature and contents
        step = int(torch.load(resume_from, weights_only=True, map_location="cpu")["global_step"])
        tracking.drop_rows_from_step(output_dir, step, prefix=f"{name}/" if name else "")
    trainer.fit(module, datamodule=datamodule, ckpt_path=resume_from, weights_only=True)
    callback = trainer.checkpoint_callback
    best_path = callback.best_model_path if callback else ""
    score = callback.best_model_score if callback is not None else None
    return (Path(best_path).name if best_path else "last.ckpt"), (math.nan if score is None else float(score))


def make_trainer(
    cfg: DictConfig, model_cfg: DictConfig, checkpoint_dir: Path, output_dir: Path, logger, setting: Setting | None
) -> pl.Trainer:
    """cfg.trainer with the model's own trainer settings and callbacks; the progress callback is told the setting."""
    callbacks = make_callbacks(model_cfg, checkpoint_dir)
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
