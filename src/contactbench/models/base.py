"""The one interface every contact model implements: fit on train/val, roll out from context frames."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.kinematics import estimate_velocities
from contactbench.recordings import Recordings, Split


@dataclass(frozen=True)
class Context:
    """What a model may see of a trajectory: its first C frames, and how many frames to return."""

    poses: np.ndarray  # [N, C, K, 7] recorded poses, world frame, quaternions w-first
    velocities: np.ndarray  # [N, C, K, 6] recorded [v, w] (world frame), or estimated from poses if absent
    lengths: np.ndarray  # [N] frames each trajectory has in total (context included)

    @property
    def n_context(self) -> int:
        return self.poses.shape[1]

    @property
    def horizon(self) -> int:
        """Frames to return per trajectory: the longest length."""
        return int(self.lengths.max())


def make_context(split: Split, dt: float, context_frames: int) -> Context:
    """The shared protocol: the first `context_frames` frames, with velocities given or estimated."""
    if context_frames < 2:
        raise ContactbenchError(f"context_frames must be at least 2 to define a velocity, got {context_frames}")
    if split.lengths.min() <= context_frames:
        short = int(np.argmin(split.lengths))
        raise ContactbenchError(
            f"trajectory {short} has {split.lengths[short]} frames; the protocol needs more than "
            f"context_frames={context_frames}"
        )
    poses = split.poses[:, :context_frames]
    if split.velocities is not None:
        velocities = split.velocities[:, :context_frames]
    else:
        velocities = estimate_velocities(poses, dt)
    return Context(poses=poses, velocities=velocities, lengths=split.lengths)


class ContactModel(ABC):
    """A contact model. `fit` may use only the train and val splits; `rollout` only the context."""

    name: str = "model"

    def fit(self, dataset: Recordings) -> None:  # noqa: B027 (optional: analytical models have nothing to fit)
        """Fit on dataset.split('train'); select on dataset.split('val')."""

    @abstractmethod
    def rollout(self, dataset: Recordings, context: Context) -> np.ndarray:
        """Predicted poses [N, context.horizon, K, 7]; the first C frames are the context itself.

        `dataset` supplies the scene only (meta: dt, gravity, floor; meshes); a model must not read its splits here.
        """

    def fitted_state(self) -> dict:
        """What `fit` learned, as JSON numbers, strings and lists of them: train.py writes it to the run folder's
        fitted.json (never a pickle) and evaluate.py gives it back through `load_fitted_state`. Lightning models keep
        theirs in checkpoints instead."""
        return {}

    def load_fitted_state(self, state: dict) -> None:
        """Become the model `fitted_state` described (override both, or neither)."""
        if state:
            raise ContactbenchError(
                f"model {self.name!r} does not load a fitted state, yet its run folder holds one "
                f"({', '.join(sorted(state))}): implement load_fitted_state beside fitted_state"
            )

    @property
    def learns(self) -> bool:
        """Whether this model's class fits anything (overrides `fit`)."""
        return type(self).fit is not ContactModel.fit
