"""Equation (1) of the paper for many candidate parameter sets at once, on rollouts of the shared protocol."""

from __future__ import annotations

import concurrent.futures
import logging
from dataclasses import dataclass

import numpy as np

from contactbench.metrics import configuration_error
from contactbench.protocol import Context, make_context, scored_frames, trajectory_means
from contactbench.recordings import Recordings
from contactbench.sim.mujoco_scene import ContactParameters
from contactbench.sim.rollout import MujocoRollouts

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Evaluation:
    losses: np.ndarray  # [B] finite: unstable or timed-out candidates carry the penalty
    unstable: np.ndarray  # [B] bool


def subset(context: Context, indices: np.ndarray) -> Context:
    return Context(context.poses[indices], context.velocities[indices], context.lengths[indices])


class ConfigurationObjective:
    """Mean over trajectories of the per-frame configuration error (eq. 1) on the predicted frames.

    A candidate whose rollout diverges, leaves the finite numbers or does not come back within `timeout_s`
    scores `unstable_penalty` (finite, so the optimiser carries on and learns to avoid the region).
    """

    def __init__(
        self,
        dataset: Recordings,
        split: str,
        context_frames: int,
        rollouts: MujocoRollouts,
        *,
        unstable_penalty: float = 1e3,
        timeout_s: float = 120.0,
        position_exponent: int = 1,
    ):
        recorded = dataset.split(split)
        self.context = make_context(recorded, dataset.dt, context_frames)
        self.truth = recorded.poses
        self.widths = dataset.widths()
        self.rollouts = rollouts
        self.unstable_penalty = float(unstable_penalty)
        self.timeout_s = float(timeout_s)
        self.position_exponent = int(position_exponent)
        self._watchdog = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="sysid-rollout")

    @property
    def n_trajectories(self) -> int:
        return len(self.truth)

    def __call__(self, candidates: list[ContactParameters], indices: np.ndarray | None = None) -> Evaluation:
        indices = np.arange(self.n_trajectories) if indices is None else np.asarray(indices)
        context = subset(self.context, indices)
        future = self._watchdog.submit(self.rollouts.rollout_context, context, candidates)
        try:
            result = future.result(timeout=self.timeout_s)
        except concurrent.futures.TimeoutError:
            # The native call cannot be interrupted: give it its own executor and data, count everything as failed.
            log.warning(
                "rollout of %d candidates did not return within %.0f s: treated as failed",
                len(candidates),
                self.timeout_s,
            )
            self._watchdog = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="sysid-rollout")
            self.rollouts.renew_data()
            return Evaluation(np.full(len(candidates), self.unstable_penalty), np.ones(len(candidates), dtype=bool))
        horizon = context.horizon
        mask = scored_frames(context.lengths, horizon, context.n_context)  # [n, T]
        with np.errstate(invalid="ignore", over="ignore"):
            errors = configuration_error(
                self.truth[indices, :horizon], result.poses, self.widths, self.position_exponent
            )  # [B, n, T]
            losses = trajectory_means(errors, mask).mean(axis=-1)
        # Frames past a trajectory's end are simulated (the batch shares one horizon) but never scored: a candidate
        # is unstable only where it is judged.
        unstable = (result.unstable_frames & mask).any(axis=(-1, -2)) | ~np.isfinite(losses)
        losses = np.where(unstable, self.unstable_penalty, np.minimum(losses, self.unstable_penalty))
        return Evaluation(losses, unstable)

    def close(self) -> None:
        self._watchdog.shutdown(wait=False, cancel_futures=True)
