"""The one interface every contact model implements: fit on train/val, roll out from context frames."""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.protocol import Context
from contactbench.recordings import Recordings, Scene


class ContactModel(ABC):
    """A contact model. `fit` may use only the train and val splits; `rollout` only the context."""

    name: str = "model"

    def fit(self, dataset: Recordings) -> None:  # noqa: B027 (optional: analytical models have nothing to fit)
        """Fit on dataset.split('train'); select on dataset.split('val')."""

    @abstractmethod
    def rollout(self, scene: Scene, context: Context) -> np.ndarray:
        """Predicted poses [N, context.horizon, K, 7]; the first C frames are the context itself.

        `scene`: bodies, meshes, dt, gravity, floor (no trajectories); `context`: the trajectories' first C frames.
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

    def scene_files(self, dataset: Recordings) -> dict[str, str]:
        """The scene this model simulates `dataset` in, in its engine's own format ({relative path: text}: MJCF,
        URDF, SDFormat and their meshes), if it is engine-based; else {}."""
        return {}

    @property
    def learns(self) -> bool:
        """Whether this model's class fits anything (overrides `fit`)."""
        return type(self).fit is not ContactModel.fit
