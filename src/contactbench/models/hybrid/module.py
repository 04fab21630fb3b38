"""The hybrid contact model (paper §4.4) in Lightning: a friction-wrench regressor and its rollout through the LCP.

Training data are the in-contact transitions of the train and val splits (`inverse.transitions_from_split`):
inputs `features.body_features` of the state at frame t, targets the body-frame friction wrench of the transition
(N, N m). Inputs and targets are standardised with train-split statistics kept as buffers, so a checkpoint alone
restores the model; the loss is the mean squared error of the standardised wrench. The rollout repeats: predict the
friction wrench (only for bodies near the floor, the transitions the regressor was trained on; in free flight there
is no friction), keep it from adding energy (`lcp.dissipative_friction`), solve the frictionless LCP for the normal
impulses at the vertices, integrate (`lcp.frictionless_step`).

Model selection rolls the model out on the val split at every validation (`models.selection.ValRollouts`, as for every
Lightning-trained model) and logs its position error as `val/pos_err` (the config early-stops and checkpoints on it).
The one-step loss is a poor proxy there: it is dominated
by impacts, which the data (PyBullet, whose contacts penetrate and push out over several steps) resolve differently
from our one-step LCP, and on frictioncubes (mu = 0.5) the rollout error was lowest after a few epochs and grew while
val/loss kept falling (0.46 -> 1.1 cube widths over 40 epochs).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pytorch_lightning as pl
import torch
from torch import nn
from torch.utils.data import BatchSampler, DataLoader, RandomSampler, SequentialSampler, TensorDataset

from contactbench.models.base import ContactModel, ContactModule
from contactbench.models.hybrid import dynamics, features, inverse, lcp
from contactbench.models.hybrid.dynamics import SingleBodyScene, State
from contactbench.models.hybrid.lcp import ContactSettings
from contactbench.protocol import Context
from contactbench.scene import Recordings, Scene, Split

FrictionPredictor = Callable[[np.ndarray], np.ndarray]  # body features [B, 9 + V] -> body-frame friction wrench [B, 6]

# Floors on standard deviations: a constant input, or friction that is zero throughout (friction = 0), stays finite.
FEATURE_STD_FLOOR = 1e-6
TARGET_STD_FLOOR = 1e-6


def _check_context_frames(context_frames: int) -> None:
    if context_frames < 2:
        raise ValueError(
            f"the hybrid model's state needs two frames (a pose and a velocity); got context_frames={context_frames}"
        )


def training_arrays(split: Split, scene: SingleBodyScene, settings: ContactSettings) -> tuple[np.ndarray, np.ndarray]:
    """Features [M, 9 + V] and body-frame friction wrenches [M, 6] of a split's in-contact transitions."""
    transitions = inverse.transitions_from_split(split, scene, settings)
    touching = transitions.in_contact
    state = transitions.state[touching]
    wrench = features.wrench_to_body(state.orientation, transitions.friction[touching]) / scene.dt
    return features.body_features(state, scene), wrench


class HybridDataModule(pl.LightningDataModule):
    """Transitions of the train and val splits (never test) as (features, friction wrench) pairs."""

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int = 6,
        batch_size: int = 512,
        contact_margin: float = 0.05,
        num_workers: int = 0,
    ):
        super().__init__()
        self.scene = dynamics.single_body_scene(dataset)
        _check_context_frames(context_frames)
        self.dataset = dataset
        self.batch_size = batch_size
        self.settings = ContactSettings(contact_margin=contact_margin)
        self.num_workers = num_workers
        self.arrays: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}

    def setup(self, stage: str | None = None) -> None:
        for name in ("train", "val"):
            if name in self.arrays:
                continue
            inputs, targets = training_arrays(self.dataset.split(name), self.scene, self.settings)
            if len(inputs) == 0:
                raise ValueError(
                    f"{self.dataset.name}/{name}: no transition comes near the floor; the hybrid model has no "
                    "friction to learn"
                )
            self.arrays[name] = (
                torch.as_tensor(inputs, dtype=torch.float32),
                torch.as_tensor(targets, dtype=torch.float32),
            )

    @property
    def statistics(self) -> dict[str, torch.Tensor]:
        """Train-split means and standard deviations of inputs and targets."""
        inputs, targets = self.arrays["train"]
        return {
            "feature_mean": inputs.mean(dim=0),
            "feature_std": inputs.std(dim=0, unbiased=False).clamp_min(FEATURE_STD_FLOOR),
            "target_mean": targets.mean(dim=0),
            "target_std": targets.std(dim=0, unbiased=False).clamp_min(TARGET_STD_FLOOR),
        }

    def _loader(self, name: str, sampler) -> DataLoader:
        # Whole batches are indexed at once (batch_size=None): per-sample indexing and collation cost ten times the
        # step.
        batches = BatchSampler(sampler, batch_size=self.batch_size, drop_last=False)
        return DataLoader(
            TensorDataset(*self.arrays[name]), sampler=batches, batch_size=None, num_workers=self.num_workers
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", RandomSampler(range(len(self.arrays["train"][0]))))

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", SequentialSampler(range(len(self.arrays["val"][0]))))


class HybridModule(ContactModule):
    """MLP (ReLU; 512, 360, 180 hidden units by default) from body features to the body-frame friction wrench."""

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int = 6,
        hidden: Sequence[int] = (512, 360, 180),
        lr: float = 5e-4,
        contact_margin: float = 0.05,
        stabilisation: float = 0.2,
        restitution: float = 0.0,
    ):
        super().__init__()
        scene = dynamics.single_body_scene(dataset)
        _check_context_frames(context_frames)
        hidden = tuple(int(width) for width in hidden)  # plain ints: a checkpoint must open with weights_only=True
        self.save_hyperparameters(ignore=["dataset"], logger=False)  # the run logs curated params itself
        self.dataset = dataset  # val rollouts select the model (ValRollouts)
        self.settings = ContactSettings(
            contact_margin=contact_margin, stabilisation=stabilisation, restitution=restitution
        )
        widths = (features.feature_count(scene.body), *hidden)
        layers: list[nn.Module] = []
        for width_in, width_out in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(width_in, width_out), nn.ReLU()]
        self.network = nn.Sequential(*layers, nn.Linear(widths[-1], 6))
        self.register_buffer("feature_mean", torch.zeros(widths[0]))
        self.register_buffer("feature_std", torch.ones(widths[0]))
        self.register_buffer("target_mean", torch.zeros(6))
        self.register_buffer("target_std", torch.ones(6))

    def setup(self, stage: str) -> None:
        if stage != "fit":
            return
        datamodule = self.trainer.datamodule
        if not isinstance(datamodule, HybridDataModule):
            raise TypeError(f"HybridModule trains with a HybridDataModule, got {type(datamodule).__name__}")
        if datamodule.settings.contact_margin != self.settings.contact_margin:
            raise ValueError(
                f"contact_margin differs between the data module ({datamodule.settings.contact_margin}) and the module "
                f"({self.settings.contact_margin}); the regressor would be used on transitions it was not trained on"
            )
        for name, value in datamodule.statistics.items():
            getattr(self, name).copy_(value)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """Body-frame friction wrench [B, 6] (N, N m) from features [B, 9 + V]."""
        return self.target_mean + self.target_std * self.network((inputs - self.feature_mean) / self.feature_std)

    def _loss(self, batch: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        inputs, targets = batch
        prediction = self.network((inputs - self.feature_mean) / self.feature_std)
        return nn.functional.mse_loss(prediction, (targets - self.target_mean) / self.target_std)

    def training_step(self, batch: tuple[torch.Tensor, torch.Tensor], batch_index: int) -> torch.Tensor:
        loss = self._loss(batch)
        self.log("train/loss", loss, on_step=False, on_epoch=True, batch_size=len(batch[0]))
        return loss

    def validation_step(self, batch: tuple[torch.Tensor, torch.Tensor], batch_index: int) -> None:
        self.log("val/loss", self._loss(batch), on_step=False, on_epoch=True, prog_bar=True, batch_size=len(batch[0]))

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=self.hparams.lr)

    def predict_friction(self, inputs: np.ndarray) -> np.ndarray:
        """NumPy face of `forward` for the rollout."""
        self.eval()
        with torch.no_grad():
            tensor = torch.as_tensor(inputs, dtype=torch.float32, device=self.device)
            return self(tensor).cpu().numpy().astype(np.float64)

    def to_contact_model(self) -> HybridContactModel:
        return HybridContactModel(self.predict_friction, self.settings)


class HybridContactModel(ContactModel):
    """Rollout: learned friction wrench (made dissipative), then the frictionless LCP for the normal impulses, then
    integration."""

    name = "hybrid"

    def __init__(self, predict_friction: FrictionPredictor, settings: ContactSettings = ContactSettings()):
        self.predict_friction = predict_friction
        self.settings = settings

    def step(self, state: State, scene: SingleBodyScene) -> State:
        """States [B] one frame later."""
        friction = np.zeros(state.linear.shape[:-1] + (6,))
        touching = lcp.in_contact(state, scene, self.settings)
        if touching.any():
            near = state[touching]
            wrench = self.predict_friction(features.body_features(near, scene))
            friction[touching] = lcp.dissipative_friction(
                near, scene, features.wrench_to_world(near.orientation, wrench) * scene.dt
            )
        return lcp.frictionless_step(state, scene, friction, self.settings)[0]

    def rollout(self, scene: Scene, context: Context) -> np.ndarray:
        """Poses [N, horizon, 1, 7]; the state starts from the last two context poses (backward difference), which
        is the velocity convention the regressor was trained with, rather than from recorded (filtered) velocities."""
        body_scene = dynamics.single_body_scene(scene)
        state = dynamics.states_from_poses(context.poses[:, -2:, 0], body_scene.body, body_scene.dt)[:, -1]
        poses = np.empty((len(context.poses), context.horizon, 1, 7))
        poses[:, : context.n_context] = context.poses
        for frame in range(context.n_context, context.horizon):
            state = self.step(state, body_scene)
            poses[:, frame, 0] = dynamics.poses_from_states(state, body_scene.body)
        return poses
