"""The contract every model satisfies, read as the spec for a model of one's own.

A model's YAML says `kind: analytical` or `kind: lightning`:

- analytical: `contact_model._target_` builds a `ContactModel`; train.py calls `fit`, writes `fitted_state()` to the
  run folder's fitted.json, and evaluate.py rebuilds the model from its YAML and calls `load_fitted_state`.
- lightning: `module._target_` builds a `ContactModule` (a LightningModule) and `datamodule._target_` its data, both
  called with `dataset=` and `context_frames=` beside their YAML settings; Lightning fits it with the YAML's
  `callbacks`, the checkpoint that scored best on val is kept (loaded back with weights_only=True), and its
  `to_contact_model()` is what is scored.

What fits, selects, restores and scores a model calls only what is written here.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
import pytorch_lightning as pl

from contactbench.errors import ContactbenchError
from contactbench.protocol import Context
from contactbench.recordings import Recordings, Scene


class ContactModel(ABC):
    """A contact model. `fit` may use only the train and val splits; `rollout` only the context."""

    name: str = "model"
    # The simulator it rolls out with (sim/engines.py: mujoco, bullet, drake), None for one that simulates by itself (a
    # learned model). On data that engine made, its score says how well it finds its own parameters, not how good it
    # is: runs.py marks its scores so (sim/engines.made_by) and the report ranks it with none.
    engine: str | None = None

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


class ContactModule(pl.LightningModule, ABC):
    """A model trained by Lightning (`kind: lightning`). Its constructor takes `dataset` (the Recordings it trains
    on: train and val splits) and `context_frames` beside its YAML's `module` settings, keeps the dataset as
    `self.dataset` and saves its hyperparameters (`self.save_hyperparameters(ignore=["dataset"])`): a checkpoint
    restores the module from them, given the dataset again.

    It is selected on val by `models.selection.ValRollouts`, listed in its YAML's callbacks: at every validation that
    rolls `selection_candidate()` out on val and logs val/pos_err, which the checkpoint callback monitors."""

    dataset: Recordings

    @property
    def context_frames(self) -> int:
        """Frames every rollout is given before it predicts (the run's `context_frames`, saved with the module)."""
        return int(self.hparams.context_frames)

    @abstractmethod
    def to_contact_model(self) -> ContactModel:
        """The model this module's weights or parameters define, as it is scored."""

    def selection_candidate(self) -> ContactModel:
        """What val rollouts score for checkpoint selection: by default the scored model itself (the residual model
        scores its correction even while the identified engine alone is ahead, and chooses between them later)."""
        return self.to_contact_model()

    def record_selection(self, errors: dict[str, float]) -> None:  # noqa: B027 (optional: most modules keep nothing)
        """Told each validation's val rollout errors ({'pos_err', 'rot_err'}), for a module that keeps them."""

    def fitted_summary(self) -> dict:
        """What the selected checkpoint learned, as JSON, added to the run folder's fitted.json (identified
        parameters, a choice made on val); {} by default."""
        return {}


def require_contract(built: object, contract: type, node: str) -> None:
    """Refuse what a model's YAML built (`node`._target_) if it is not the class the contract asks for."""
    made = built if isinstance(built, type) else type(built)
    if not issubclass(made, contract):
        raise ContactbenchError(
            f"{node}._target_ is {made.__module__}.{made.__qualname__}, not a {contract.__name__} "
            f"(expected a subclass of {contract.__module__}.{contract.__name__}; docs/ADDING_A_MODEL.md)"
        )
