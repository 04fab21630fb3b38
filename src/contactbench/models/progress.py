"""Where a long fit is: one log line per validation when the console is a log file or a pipe, one bar over the whole
fit at a terminal. Both name the setting when a model is fitted once per setting of its `choose_on_val` grid (the
GNN's noise levels: "setting 2/3 (noise_std=0.0002)") and count steps to the fit's end, not batches of an epoch."""

from __future__ import annotations

import logging
import math

import pytorch_lightning as pl
from pytorch_lightning.callbacks import TQDMProgressBar

log = logging.getLogger(__name__)

Setting = tuple[int, int, str]  # k, N, "noise_std=0.0002"


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


class FitProgress:
    """What a progress callback is told by the fitting code (fitting.make_trainer): which setting of the model's
    `choose_on_val` grid this fit is, or None for a model fitted once."""

    setting: Setting | None = None


class ValidationLines(FitProgress, pl.Callback):
    """One log line per validation: where the fit is and the val score it is selected on."""

    def __init__(self, model: str):
        self.model = model

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        score = trainer.callback_metrics.get("val/pos_err")
        found = f": val/pos_err {float(score):.4f}" if score is not None else ""
        log.info("%s%s", where(self.model, self.setting, steps_done(trainer), steps_total(trainer)), found)


class FitBar(FitProgress, TQDMProgressBar):
    """Lightning's bar, named by model and setting and counting steps to the end of the fit (Lightning's counts one
    epoch's batches and starts again at the next)."""

    def __init__(self, model: str):
        super().__init__()
        self.model = model

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


def fit_progress(model: str, bar: bool = False) -> FitProgress:
    """The bar where the trainer shows one (trainer.enable_progress_bar: at a terminal), else the log lines."""
    return FitBar(model) if bar else ValidationLines(model)
