"""Model selection for every Lightning-trained model: val rollouts through the shared protocol, one key to monitor."""

from __future__ import annotations

import numpy as np
import pytorch_lightning as pl
from pytorch_lightning.callbacks import WeightAveraging

from contactbench.metrics import position_error, rotation_error
from contactbench.models.base import ContactModel, ContactModule
from contactbench.protocol import make_context, scored_frames, trajectory_means
from contactbench.recordings import Recordings

POSITION_KEY, ROTATION_KEY = "val/pos_err", "val/rot_err"


def evenly_spaced(count: int, chosen: int | None) -> np.ndarray:
    """`chosen` indices spread evenly over range(count) (all of them when chosen is None or not smaller)."""
    if chosen is None or chosen >= count:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, chosen).round().astype(np.int64))


def rollout_errors(
    model: ContactModel, dataset: Recordings, split_name: str, context_frames: int, trajectories: int | None = None
) -> dict[str, float]:
    """Position (/ width) and rotation (rad) error of the model's rollouts of an evenly spaced subset of a split's
    trajectories (all: None), each the mean over a trajectory's scored frames, then over trajectories — the numbers
    `metrics.compute_metrics` reports, without the penetration measures."""
    split = dataset.split(split_name)
    long_enough = np.flatnonzero(split.lengths > context_frames)
    chosen = split.select(long_enough[evenly_spaced(len(long_enough), trajectories)])
    context = make_context(chosen, dataset.dt, context_frames)
    predicted = model.rollout(dataset.scene, context)
    recorded = chosen.poses[:, : context.horizon]
    scored = scored_frames(chosen.lengths, context.horizon, context_frames)
    per_frame = {
        "pos_err": position_error(recorded, predicted, dataset.widths()).mean(axis=-1),
        "rot_err": rotation_error(recorded, predicted).mean(axis=-1),
    }
    return {name: float(trajectory_means(values, scored).mean()) for name, values in per_frame.items()}


class ValRollouts(pl.Callback):
    """At every validation, rolls the module's contact model out on val from the shared protocol's context and logs
    `val/pos_err` and `val/rot_err`: what checkpoints and early stopping monitor, the same for every model.

    What it scores is the module's `selection_candidate()` on its `dataset` with its `context_frames`, and
    `record_selection(errors)` is told the scores (models/base.py: ContactModule).
    Rolled out at the start of the validation epoch, after a weight-averaging callback listed before this one has
    swapped its average in (the average is what the checkpoint keeps); one listed after it is refused.
    """

    def __init__(self, trajectories: int | None = None):
        self.trajectories = trajectories

    def setup(self, trainer: pl.Trainer, pl_module: ContactModule, stage: str) -> None:
        order = trainer.callbacks.index(self)
        if any(isinstance(callback, WeightAveraging) for callback in trainer.callbacks[order + 1 :]):
            raise ValueError(
                "ValRollouts is listed before a weight-averaging callback: it would score the raw weights while the "
                "checkpoint keeps the average; list the selection callback after it"
            )

    def on_validation_epoch_start(self, trainer: pl.Trainer, pl_module: ContactModule) -> None:
        if trainer.sanity_checking:
            return
        errors = rollout_errors(
            pl_module.selection_candidate(), pl_module.dataset, "val", pl_module.context_frames, self.trajectories
        )
        pl_module.record_selection(errors)
        pl_module.log(POSITION_KEY, errors["pos_err"], prog_bar=True)
        pl_module.log(ROTATION_KEY, errors["rot_err"])
