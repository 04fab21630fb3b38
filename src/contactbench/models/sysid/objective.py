"""Equation (1) of the paper for many candidate parameter sets at once, on rollouts of the shared protocol."""

from __future__ import annotations

import concurrent.futures
import logging
import time
from dataclasses import dataclass

import numpy as np

from contactbench.metrics import configuration_error
from contactbench.protocol import Context, make_context, scored_frames, trajectory_means
from contactbench.scene import Recordings
from contactbench.sim.mujoco_scene import ContactParameters
from contactbench.sim.rollout import Rollouts

log = logging.getLogger(__name__)
# One native call per group of tosses of similar length: a call steps every toss to the longest one's end, so one
# call for all wastes many steps on the real cube's uneven tosses and four waste few
# (docs/results/calibration.md).
LENGTH_GROUPS = 4


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
        rollouts: Rollouts,
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
        steps = context.lengths - context.n_context  # predicted frames each trajectory is scored on
        # Laid out over the whole horizon as one rollout of the batch would have them, so that every loss is summed as
        # before to the last bit; frames that are not scored stay zero (trajectory_means leaves them out anyway).
        errors = np.zeros((len(candidates), len(indices), context.horizon))
        unstable = np.empty((len(candidates), len(indices)), dtype=bool)
        deadline = time.monotonic() + self.timeout_s
        # Frames past a trajectory's end are never scored (a quarter of the real cube's steps if the batch shared one
        # horizon): each group of alike lengths is simulated only as far as its longest, and a candidate is unstable
        # only where it is judged.
        for group in length_groups(steps):
            horizon = int(steps[group].max())
            future = self._watchdog.submit(
                self.rollouts.simulate, candidates, context.poses[group, -1], context.velocities[group, -1], horizon
            )
            try:
                result = future.result(timeout=max(deadline - time.monotonic(), 0.0))
            except concurrent.futures.TimeoutError:
                return self._timed_out(len(candidates))
            predicted = slice(context.n_context, context.n_context + horizon)
            with np.errstate(invalid="ignore", over="ignore"):
                errors[:, group, predicted] = configuration_error(
                    self.truth[indices[group], predicted], result.poses, self.widths, self.position_exponent
                )
            unstable[:, group] = (result.unstable_frames & (np.arange(horizon) < steps[group, None])).any(axis=-1)
        with np.errstate(invalid="ignore", over="ignore"):
            scored = scored_frames(context.lengths, context.horizon, context.n_context)  # [n, T]
            losses = trajectory_means(errors, scored).mean(axis=-1)
        unstable = unstable.any(axis=-1) | ~np.isfinite(losses)
        losses = np.where(unstable, self.unstable_penalty, np.minimum(losses, self.unstable_penalty))
        return Evaluation(losses, unstable)

    def _timed_out(self, n_candidates: int) -> Evaluation:
        # The native call cannot be interrupted: give it its own executor and data, count everything as failed.
        log.warning(
            "rollout of %d candidates did not return within %.0f s: treated as failed", n_candidates, self.timeout_s
        )
        self._watchdog = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="sysid-rollout")
        self.rollouts.renew_data()
        return Evaluation(np.full(n_candidates, self.unstable_penalty), np.ones(n_candidates, dtype=bool))

    def close(self) -> None:
        self._watchdog.shutdown(wait=False, cancel_futures=True)


def length_groups(steps: np.ndarray, count: int = LENGTH_GROUPS) -> list[np.ndarray]:
    """Indices of `steps` in up to `count` groups of consecutive lengths, about equally many in each; groups that
    would end at the same length are one (tosses of one length, as generated datasets have, make a single group)."""
    groups: list[np.ndarray] = []
    for group in np.array_split(np.argsort(steps, kind="stable"), count):
        if len(group) and groups and steps[groups[-1][-1]] == steps[group[-1]]:
            groups[-1] = np.concatenate([groups[-1], group])
        elif len(group):
            groups.append(group)
    return groups
