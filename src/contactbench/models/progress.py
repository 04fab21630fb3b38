"""Where a long fit is: one log line per validation when the console is a log file or a pipe, one bar over the whole
fit at a terminal. Both name the setting when a model is fitted once per setting of its `choose_on_val` grid (the
GNN's noise levels: "setting 2/3 (noise_std=0.0002)") and count steps to the fit's end, not batches of an epoch."""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Mapping

import pytorch_lightning as pl
from omegaconf import DictConfig, OmegaConf
from pytorch_lightning.callbacks import TQDMProgressBar

log = logging.getLogger(__name__)

Setting = tuple[int, int, str]  # k, N, "noise_std=0.0002"


def setting_of(grid: Mapping | None, hparams: Mapping) -> Setting | None:
    """Which setting of a `choose_on_val` grid ({module: {noise_std: [values]}}) a module was built with, in the order
    the grid's settings are fitted (runs.settings_grid); None without a grid or where the module's own settings do not
    say (a grid over the datamodule)."""
    if not grid:
        return None
    leaves = _leaves(OmegaConf.to_container(grid) if isinstance(grid, DictConfig) else dict(grid))
    if not all(key.startswith("module.") for key in leaves):
        return None
    combinations = list(itertools.product(*leaves.values()))
    for k, values in enumerate(combinations, start=1):
        chosen = dict(zip(leaves, values))
        if all(_same(_get(hparams, key.removeprefix("module.")), value) for key, value in chosen.items()):
            name = ",".join(f"{key.rsplit('.', 1)[-1]}={value:g}" for key, value in chosen.items())
            return k, len(combinations), name
    return None


def label(model: str, setting: Setting | None) -> str:
    return f"{model} setting {setting[0]}/{setting[1]} ({setting[2]})" if setting else model


def where(model: str, setting: Setting | None, step: int, total: int | None) -> str:
    """`gnn setting 2/3 (noise_std=0.0002), step 500/2500`; `sysid step 3` where the end is not known."""
    return f"{label(model, setting)}{',' if setting else ''} step {step}" + (f"/{total}" if total else "")


def steps_done(trainer: pl.Trainer) -> int:
    """Optimiser steps; a fit without an optimiser (SysID: a step is its search callback's) counts its batches."""
    return trainer.global_step if trainer.optimizers else trainer.fit_loop.epoch_loop.total_batch_idx + 1


def steps_total(trainer: pl.Trainer) -> int | None:
    total = trainer.estimated_stepping_batches if trainer.optimizers else trainer.num_training_batches
    return int(total) if math.isfinite(total) else None


class ValidationLines(pl.Callback):
    """One log line per validation: where the fit is and the val score it is selected on."""

    def __init__(self, model: str, grid: Mapping | None = None):
        self.model, self.grid, self.setting = model, grid, None

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.setting = setting_of(self.grid, pl_module.hparams)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        score = trainer.callback_metrics.get("val/pos_err")
        found = f": val/pos_err {float(score):.4f}" if score is not None else ""
        log.info("%s%s", where(self.model, self.setting, steps_done(trainer), steps_total(trainer)), found)


class FitBar(TQDMProgressBar):
    """Lightning's bar, named by model and setting and counting steps to the end of the fit (Lightning's counts one
    epoch's batches and starts again at the next)."""

    def __init__(self, model: str, grid: Mapping | None = None):
        super().__init__()
        self.model, self.grid, self.setting = model, grid, None

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.setting = setting_of(self.grid, pl_module.hparams)

    def init_train_tqdm(self):
        bar = super().init_train_tqdm()
        bar.unit = "step"
        return bar

    def on_train_epoch_start(self, trainer: pl.Trainer, *_) -> None:
        bar = self.train_progress_bar
        bar.total = steps_total(trainer)
        bar.set_description(label(self.model, self.setting))
        self._show(trainer)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, *_) -> None:
        self._show(trainer)
        self.train_progress_bar.set_postfix(self.get_metrics(trainer, pl_module), refresh=False)

    def _show(self, trainer: pl.Trainer) -> None:
        bar = self.train_progress_bar
        if not bar.disable:
            bar.n = steps_done(trainer)
            bar.refresh()


def fit_progress(model: str, grid: Mapping | None = None, bar: bool = False) -> pl.Callback:
    """The bar where the trainer shows one (trainer.enable_progress_bar: at a terminal), else the log lines."""
    return FitBar(model, grid) if bar else ValidationLines(model, grid)


def _leaves(tree: dict, prefix: str = "") -> dict[str, list]:
    found = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            found.update(_leaves(value, f"{prefix}{key}."))
        else:
            found[f"{prefix}{key}"] = list(value)
    return found


def _get(tree: Mapping, dotted: str):
    for part in dotted.split("."):
        tree = tree.get(part) if isinstance(tree, Mapping) else None
    return tree


def _same(a, b) -> bool:
    try:
        return math.isclose(float(a), float(b), rel_tol=1e-9)
    except (TypeError, ValueError):
        return a == b
