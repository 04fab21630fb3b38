"""The shared protocol, below every model and metric: what a model sees of a trajectory (its context) and which of
its frames are scored (those after the context, up to the trajectory's end)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.kinematics import fit_velocities
from contactbench.scene import Split


@dataclass(frozen=True)
class Context:
    """What a model may see of a trajectory: its first C frames, and how many frames to return."""

    poses: np.ndarray  # [N, C, K, 7] recorded poses, world frame, quaternions w-first
    velocities: np.ndarray  # [N, C, K, 6] recorded [v, w] (world frame), or fitted to the context poses if absent
    lengths: np.ndarray  # [N] frames each trajectory has in total (context included)

    @property
    def n_context(self) -> int:
        return self.poses.shape[1]

    @property
    def horizon(self) -> int:
        """Frames to return per trajectory: the longest length."""
        return int(self.lengths.max())


def make_context(split: Split, dt: float, context_frames: int) -> Context:
    """The shared protocol: the first `context_frames` frames, with velocities given or, where the recordings have
    none, fitted to the context poses by least squares (`kinematics.fit_velocities`: tracker noise is averaged
    over the context instead of being read twice by a backward difference)."""
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
        velocities = fit_velocities(poses, dt)
    return Context(poses=poses, velocities=velocities, lengths=split.lengths)


def scored_frames(lengths: np.ndarray, horizon: int, context_frames: int) -> np.ndarray:
    """[N, horizon] True at the frames a trajectory is scored on: from context_frames to its last frame."""
    frames = np.arange(horizon)[None, :]
    return (frames >= context_frames) & (frames < np.asarray(lengths)[:, None])


def trajectory_means(values: np.ndarray, scored: np.ndarray) -> np.ndarray:
    """Mean of values [..., N, T] over each trajectory's scored frames [N, T]: [..., N] (every trajectory counts once,
    however long, as the paper averages)."""
    return np.where(scored, values, 0.0).sum(axis=-1) / scored.sum(axis=-1)
