"""Ballistic flight from the last context frame, then a stop: the frame it stops at is what it fits."""

from __future__ import annotations

import numpy as np

from contactbench.metrics import position_error
from contactbench.models.base import ContactModel
from contactbench.protocol import Context, make_context
from contactbench.recordings import Recordings, Scene


class BallisticThenStop(ContactModel):
    """Each body keeps its last context velocity under gravity (never below the floor) until `stop_frame`, then
    holds its pose; its orientation never changes. `fit` picks `stop_frame` on val among `candidates` frames."""

    def __init__(self, name: str = "ballistic", candidates: int = 8, context_frames: int = 6):
        self.name = name
        self.candidates = candidates
        self.context_frames = context_frames
        self.stop_frame: int | None = None

    def fit(self, dataset: Recordings) -> None:
        val = dataset.split("val")
        context = make_context(val, dataset.dt, self.context_frames)
        frames = np.arange(context.horizon)
        scored = (frames >= self.context_frames) & (frames < val.lengths[:, None])
        errors = {}
        for stop in np.linspace(self.context_frames, context.horizon, self.candidates).round().astype(int):
            self.stop_frame = int(stop)
            predicted = self.rollout(dataset.scene, context)
            per_frame = position_error(val.poses[:, : context.horizon], predicted, dataset.widths()).mean(axis=-1)
            errors[int(stop)] = float(per_frame[scored].mean())
        self.stop_frame = min(errors, key=errors.get)

    def rollout(self, scene: Scene, context: Context) -> np.ndarray:
        if self.stop_frame is None:
            raise RuntimeError("fit the model (or load its fitted state) before rolling it out")
        last = context.poses[:, -1]  # [N, K, 7]
        velocity = context.velocities[:, -1, :, :3]
        flying = np.minimum(np.arange(context.horizon - context.n_context + 1), self.stop_frame - context.n_context + 1)
        t = np.maximum(flying, 0)[None, :, None, None] * scene.dt
        positions = last[:, None, :, :3] + velocity[:, None] * t + 0.5 * scene.gravity * t**2
        lowest = scene.floor_z + scene.widths() / 2  # a body's centre stays half a width above the floor
        positions[..., 2] = np.maximum(positions[..., 2], lowest)
        future = np.concatenate([positions, np.broadcast_to(last[:, None, :, 3:], positions.shape[:-1] + (4,))], -1)
        return np.concatenate([context.poses, future[:, 1:]], axis=1)

    def fitted_state(self) -> dict:
        return {"stop_frame": self.stop_frame}

    def load_fitted_state(self, state: dict) -> None:
        self.stop_frame = int(state["stop_frame"])
