"""What the residual model trains on, read from the recordings as MuJoCo states: recorded frames, the windows stage two
rolls out from, and every one-step transition with what MuJoCo gets wrong over it (the inputs' and outputs' scales)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from contactbench import rotations
from contactbench.kinematics import estimate_velocities
from contactbench.models.residual import correction
from contactbench.models.residual.correction import Bodies
from contactbench.scene import Split
from contactbench.sim.mujoco_scene import ContactParameters, body_frame_velocities
from contactbench.sim.rollout import MujocoRollouts


def recorded_states(
    split: Split, trajectory: np.ndarray, frame: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo states qpos [M, K, 7], qvel [M, K, 6] of recorded frames (velocities as recorded, else backward
    differences)."""
    velocities = split.velocities if split.velocities is not None else estimate_velocities(split.poses, dt)
    poses = split.poses[trajectory, frame]
    qpos = np.concatenate([poses[..., :3], rotations.normalize(poses[..., 3:])], axis=-1)
    return qpos, body_frame_velocities(qpos, velocities[trajectory, frame])


def recorded_windows(
    split: Split, segments: np.ndarray, unroll: int, dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Windows [(trajectory, first frame)] of a split as MuJoCo states at their first frame (qpos [M, K, 7], qvel
    [M, K, 6]), the recorded poses of the `unroll` frames after it [M, unroll, K, 7] (past a toss's end, its last
    frame) and which of those frames the toss has [M, unroll]."""
    trajectory, first = segments[:, 0], segments[:, 1]
    qpos, qvel = recorded_states(split, trajectory, first, dt)
    frames = first[:, None] + 1 + np.arange(unroll)
    lengths = split.lengths[trajectory][:, None]
    truth = split.poses[trajectory[:, None], np.minimum(frames, lengths - 1)]
    return qpos, qvel, truth, frames < lengths


def transitions(
    split: Split,
    bodies: Bodies,
    simulator: MujocoRollouts,
    parameters: ContactParameters,
    selected: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Features [N, F] and one-step correction targets [N, 6] of every body in every transition t -> t + 1 of a split,
    from the recorded states: what MuJoCo gets wrong per step, for the scale of inputs and outputs. `selected` keeps
    some bodies only: from the recorded states before the step (qpos [M, K, 7], qvel [M, K, 6]) to a mask [M, K]."""
    trajectory, frame = np.nonzero(np.arange(split.poses.shape[1] - 1)[None, :] < split.lengths[:, None] - 1)
    qpos0, qvel0 = recorded_states(split, trajectory, frame, bodies.dt)
    m, n_bodies = qpos0.shape[:2]
    qpos1, qvel1, diverged = simulator.step(parameters, qpos0.reshape(m, -1), qvel0.reshape(m, -1))
    qpos1, qvel1 = qpos1.reshape(m, n_bodies, 7), qvel1.reshape(m, n_bodies, 6)
    keep = ~diverged
    qpos0, qvel0, qpos1, qvel1 = qpos0[keep], qvel0[keep], qpos1[keep], qvel1[keep]
    chosen = np.ones(qpos0.shape[:2], dtype=bool) if selected is None else selected(qpos0, qvel0)
    inputs = correction.features(bodies, qpos0, qvel0, qpos1, qvel1)
    recorded_next = split.poses[trajectory, frame + 1][keep]
    wanted = correction.targets(qpos0, qpos1, qvel1, recorded_next, bodies.dt)
    return inputs[chosen], wanted[chosen]


def segment_starts(split: Split) -> np.ndarray:
    """[S, 2] (trajectory, first frame) of the windows a split offers: one from every frame that has a next one (a
    window running past its toss's end is scored up to the end)."""
    return np.argwhere(np.arange(split.poses.shape[1])[None, :] + 1 < split.lengths[:, None])
