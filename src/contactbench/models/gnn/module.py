"""Lightning wrappers of the mesh GNN: training windows from train, rollout validation on val, checkpoints.

`GNNDataModule` serves windows of H + 2 consecutive frames of world vertex positions (H + 1 inputs and the next
frame), sampled uniformly over all valid windows of the train split, batch 64 (paper); its validation loader serves a
fixed, evenly spaced subset of the val split's windows for the one-step loss. `GNNModule` trains with Adam at
lr 1e-4 (paper) on the noisy one-step loss and logs `val/one_step_loss`; models are selected on val rollouts
(paper) by the configured `models.selection.ValRollouts` callback, as every Lightning-trained model is. The test
split is never read here.
Normalisation statistics are computed from the train split when fitting starts and live in buffers, so
`GNNModule.load_from_checkpoint(path, dataset=recordings, weights_only=True)` restores a usable model.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import BatchSampler, DataLoader, Dataset, Sampler, SequentialSampler

from contactbench.errors import NotApplicable
from contactbench.ground import Ground
from contactbench.models.base import ContactModel, ContactModule
from contactbench.models.gnn.graph import DEFAULT_COLLISION_RADIUS_FRACTION, MeshScene, collision_radius
from contactbench.models.gnn.rigid import RigidGNNContactModel, RigidLearnedSimulator
from contactbench.models.gnn.simulator import GNNContactModel, LearnedSimulator
from contactbench.models.selection import evenly_spaced
from contactbench.scene import Recordings, Split

LR_SCHEDULES = ("constant", "cosine")


def check_history_fits(context_frames: int, velocity_history: int) -> None:
    if context_frames < velocity_history + 1:
        raise ValueError(
            f"{velocity_history} velocities need {velocity_history + 1} context frames; the protocol gives "
            f"{context_frames}"
        )


def inertia_per_mass(dataset: Recordings, scene: MeshScene) -> np.ndarray:
    """Every body's inertia tensor per unit mass about its mesh vertices' centroid, mesh-frame axes [K, 3, 3]."""
    tensors = []
    for k, nodes in enumerate(scene.body_slices()):
        com, inertia = dataset.inertial(k)
        offset = scene.rest_vertices[nodes].mean(axis=0) - com
        mass = dataset.bodies[k].mass
        tensors.append(inertia / mass + offset @ offset * np.eye(3) - np.outer(offset, offset))
    return np.stack(tensors)


class StepSeededBatches(Sampler):
    """Batches of window indices drawn uniformly (without replacement inside a batch), batch by batch from a generator
    seeded with (seed, training step): a run resumed from any step, mid-epoch included, draws the batches an
    uninterrupted run draws. `current_step` is read when an epoch's iteration starts."""

    def __init__(self, n_windows: int, batch_size: int, seed: int, current_step: Callable[[], int]):
        self.n_windows, self.batch_size, self.seed, self.current_step = (
            n_windows,
            min(batch_size, n_windows),
            seed,
            current_step,
        )

    def __len__(self) -> int:
        return -(-self.n_windows // self.batch_size)

    def __iter__(self):
        first = self.current_step()
        for step in range(first, first + len(self)):
            yield np.random.default_rng([self.seed, step]).choice(self.n_windows, self.batch_size, replace=False)


class VertexWindows(Dataset):
    """Windows [window_frames, n, 3] (float32) of consecutive world vertex positions inside one split's trajectories.

    Meant to be indexed with a whole batch of window indices at once (a BatchSampler as the DataLoader's sampler),
    so a batch's vertices are placed in one vectorised call.
    """

    def __init__(
        self, split: Split, scene: MeshScene, window_frames: int, max_windows: int | None = None, as_poses: bool = False
    ):
        fits = np.arange(split.n_frames)[None, :] <= (split.lengths - window_frames)[:, None]
        trajectories, starts = np.nonzero(fits)
        keep = evenly_spaced(len(trajectories), max_windows)
        self.trajectories, self.starts = trajectories[keep], starts[keep]
        self.poses = split.poses
        self.scene = scene
        self.window_frames = window_frames
        self.as_poses = as_poses

    def __len__(self) -> int:
        return len(self.trajectories)

    def __getitem__(self, indices) -> torch.Tensor:
        indices = np.asarray(indices)
        frames = self.starts[indices][..., None] + np.arange(self.window_frames)
        poses = self.poses[self.trajectories[indices][..., None], frames]
        if self.as_poses:  # the rigid GNN differences poses in float64
            return torch.from_numpy(poses)
        return torch.from_numpy(self.scene.world_vertices(poses).astype(np.float32))


class GNNDataModule(pl.LightningDataModule):
    """Training windows from the train split, one-step validation windows from the val split."""

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int = 6,
        batch_size: int = 64,
        num_workers: int = 0,
        velocity_history: int = 5,
        val_windows: int | None = 4096,
        val_batch_size: int = 256,
        rigid: bool = False,
        batch_vertices: int | None = None,
        seed: int = 0,
    ):
        super().__init__()
        check_history_fits(context_frames, velocity_history)
        self.dataset = dataset
        self.scene = MeshScene.of(dataset)
        # A batch of a fixed number of vertices costs about the same for a cube or five: budgets hold for every variant.
        self.batch_size = batch_size if batch_vertices is None else max(1, batch_vertices // self.scene.n_nodes)
        self.num_workers = num_workers
        self.window_frames = velocity_history + 2
        self.val_windows = val_windows
        self.val_batch_size = val_batch_size
        self.rigid = rigid
        self.seed = seed

    def _loader(self, windows: VertexWindows, batches: Sampler) -> DataLoader:
        if len(windows) == 0:
            raise ValueError(
                f"no trajectory of dataset {self.dataset.name!r} has the {self.window_frames} frames one training "
                "window needs"
            )
        return DataLoader(
            windows,
            sampler=batches,
            batch_size=None,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        windows = VertexWindows(self.dataset.split("train"), self.scene, self.window_frames, as_poses=self.rigid)
        return self._loader(windows, StepSeededBatches(len(windows), self.batch_size, self.seed, self._current_step))

    def _current_step(self) -> int:
        return self.trainer.global_step if self.trainer is not None else 0

    def val_dataloader(self) -> DataLoader:
        windows = VertexWindows(
            self.dataset.split("val"), self.scene, self.window_frames, self.val_windows, as_poses=self.rigid
        )
        return self._loader(windows, BatchSampler(SequentialSampler(windows), self.val_batch_size, drop_last=False))


class GNNModule(ContactModule):
    """Trains the learned simulator; `to_contact_model()` gives the ContactModel the benchmark scores."""

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int = 6,
        latent_size: int = 128,
        message_passing_steps: int = 10,
        mlp_hidden_layers: int = 2,
        lr: float = 1e-4,
        noise_std: float = 3e-4,
        velocity_history: int = 5,
        collision_radius_fraction: float = DEFAULT_COLLISION_RADIUS_FRACTION,
        per_step_projection: bool = False,
        rollout_batch_size: int = 256,
        rigid: bool = False,
        contact_distance_fraction: float = 0.25,
        separate_bodies: bool = False,
        floor_gate_fraction: float | None = None,
        solid_inertia: bool = False,
        lr_schedule: str = "constant",
        seed: int = 0,
    ):
        super().__init__()
        self.save_hyperparameters(ignore=["dataset"], logger=False)  # the run logs curated params itself
        check_history_fits(context_frames, velocity_history)
        if lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {lr_schedule!r}")
        self.dataset = dataset
        scene = MeshScene.of(dataset)
        options = {
            "dt": dataset.dt,
            "floor_z": dataset.floor_z,
            "ground": Ground.of(dataset),
            "radius": collision_radius(scene.widths, collision_radius_fraction),
            "velocity_history": velocity_history,
            "latent_size": latent_size,
            "message_passing_steps": message_passing_steps,
            "hidden_layers": mlp_hidden_layers,
            "noise_std": noise_std,
        }
        if rigid:
            contact_distance = contact_distance_fraction * float(np.max(scene.widths))
            self.simulator = RigidLearnedSimulator(
                scene,
                gravity=dataset.gravity,
                contact_distance=contact_distance,
                separate_bodies=separate_bodies,
                solid_inertia=inertia_per_mass(dataset, scene) if solid_inertia else None,
                floor_gate=None if floor_gate_fraction is None else floor_gate_fraction * float(np.max(scene.widths)),
                joints=tuple(dataset.joints),
                masses=np.array([body.mass for body in dataset.bodies]),
                **options,
            )
        else:
            if dataset.joints:
                raise NotApplicable(
                    f"{dataset.name}: the paper's GNN moves every vertex on its own and keeps no joint; "
                    "model=gnn (rigid) keeps hinges"
                )
            self.simulator = LearnedSimulator(scene, **options)

    def setup(self, stage: str) -> None:
        if stage == "fit" and not bool(self.simulator.normalisation_fitted):
            self.simulator.fit_normalisation(self.dataset.split("train"))

    def optimizer(self) -> torch.optim.Optimizer:
        """Adam over every parameter, fused: one kernel for all tensors instead of a Python loop over them."""
        return torch.optim.Adam(self.parameters(), lr=self.hparams.lr, fused=True)

    def configure_optimizers(self):
        optimizer = self.optimizer()
        if self.hparams.lr_schedule == "constant":
            return optimizer
        # cosine decay to 1% of lr over the run's max_steps: large steps early, fine ones while selecting on val
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
            optimizer, T_max=max(1, self.trainer.max_steps), eta_min=0.01 * self.hparams.lr
        )
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}

    def training_step(self, batch: torch.Tensor, batch_idx: int) -> torch.Tensor:
        # noise drawn from (seed, step), like the batches: a resumed run trains exactly as an uninterrupted one
        generator = torch.Generator(device=batch.device).manual_seed(
            int(np.random.SeedSequence([self.hparams.seed, self.global_step]).generate_state(1)[0])
        )
        loss = self.simulator.loss(batch, add_noise=True, generator=generator)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(batch))
        return loss

    def validation_step(self, batch: torch.Tensor, batch_idx: int) -> None:
        self.log("val/one_step_loss", self.simulator.loss(batch, add_noise=False), batch_size=len(batch))

    def on_train_start(self) -> None:
        self._clock = {"started": time.perf_counter(), "validating": 0.0, "validation_started": 0.0}

    def on_validation_start(self) -> None:  # before every callback's validation-epoch hooks (the val rollouts)
        if hasattr(self, "_clock"):
            self._clock["validation_started"] = time.perf_counter()

    def on_validation_epoch_end(self) -> None:
        if hasattr(self, "_clock"):  # training seconds in this process, validation excluded: learning curves' x-axis
            clock = self._clock
            self.log("train/seconds", clock["validation_started"] - clock["started"] - clock["validating"])
            clock["validating"] += time.perf_counter() - clock["validation_started"]

    def to_contact_model(self) -> ContactModel:
        if not bool(self.simulator.normalisation_fitted):
            raise RuntimeError("the GNN has no normalisation statistics yet: train it (or load a checkpoint) first")
        if self.hparams.rigid:
            return RigidGNNContactModel(self.simulator, self.hparams.rollout_batch_size)
        return GNNContactModel(self.simulator, self.hparams.per_step_projection, self.hparams.rollout_batch_size)
