"""Short-horizon residuals: restart the simulator from the recorded state every few frames and compare."""

from __future__ import annotations

import hashlib
import pickle
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np

from contactbench import rotations
from contactbench.diagnosis.phases import FREE, IMPACT, PHASES, clearances, label_phases, recorded_velocities
from contactbench.scene import Recordings, Split
from contactbench.sim.engines import engine

# Residual components, world frame: linear (normal = along gravity, tangential), angular (normal, tangential),
# and the angular residual in the body frame.
COMPONENTS = ("linear_normal", "linear_tangential", "angular_normal", "angular_tangential")
# Every residual entry from the frame MuJoCo diverged at scores this much, and no entry more (finite: fits carry on).
UNSTABLE_RESIDUAL = 10.0
# Bytes of residuals a SegmentSimulator keeps, least recently used first out: a diagnosis asks for the same parameter
# set again and again (a candidate effect at its "off" start is the model before it; a least-squares fit ends where its
# last step was; the model of a round is scored on val in several judgements), and a stepped engine's evaluation costs
# seconds.
RESIDUAL_CACHE_BYTES = 128 * 2**20
# Body widths the lowest vertex keeps above the recorded floor in an airborne segment: a floor fitted a few degrees
# tilted or a centimetre higher must not reach it (a rolling friction "gained" in segments merely labelled free next
# to a tilted floor).
AIRBORNE_CLEARANCE = 0.25


@dataclass(frozen=True)
class Segments:
    """Segments of `length` frames cut from a split: where they start and what the recordings say happens."""

    trajectory: np.ndarray  # [M] trajectory of each segment
    start: np.ndarray  # [M] frame the simulator is reset to
    poses0: np.ndarray  # [M, K, 7]
    velocities0: np.ndarray  # [M, K, 6]
    truth: np.ndarray  # [M, L, K, 7] recorded frames start+1 .. start+L
    phase: np.ndarray  # [M, K] phase each body spends the segment in (an impact anywhere in it counts)
    airborne: np.ndarray  # [M] every body flies clear of the floor from the start frame to the segment's last
    length: int
    widths: np.ndarray  # [K]

    @property
    def count(self) -> int:
        return len(self.start)

    def of_trajectories(self, count: int) -> Segments:
        """The segments of the first `count` trajectories."""
        kept = self.trajectory < count
        return replace(
            self,
            **{
                name: getattr(self, name)[kept]
                for name in ("trajectory", "start", "poses0", "velocities0", "truth", "phase", "airborne")
            },
        )


def cut_segments(dataset: Recordings, split: Split, length: int, first_frame: int = 1) -> Segments:
    """Back-to-back segments of `length` frames from `first_frame` (frame 0 may lack a velocity estimate)."""
    velocities = recorded_velocities(split, dataset.dt)
    labels = label_phases(dataset, split)
    trajectory, start = [], []
    for n, frames in enumerate(split.lengths):
        starts = np.arange(first_frame, int(frames) - length, length)
        trajectory.append(np.full(len(starts), n))
        start.append(starts)
    trajectory, start = np.concatenate(trajectory), np.concatenate(start)
    window = start[:, None] + np.arange(1, length + 1)[None, :]
    truth = split.poses[trajectory[:, None], window]
    # The phase a body spends a segment in: impact if it has one anywhere, else its most frequent phase.
    counts = (labels[trajectory[:, None], window][..., None] == np.arange(len(PHASES))).sum(axis=1)  # [M, K, phases]
    phase = np.where(counts[..., IMPACT] > 0, IMPACT, counts.argmax(axis=-1)).astype(np.int8)
    spans = start[:, None] + np.arange(length + 1)[None, :]  # the start frame and the window
    clear = (labels[trajectory[:, None], spans] == FREE) & (
        clearances(dataset, split)[trajectory[:, None], spans] >= AIRBORNE_CLEARANCE
    )
    airborne = clear.all(axis=(1, 2))
    return Segments(
        trajectory,
        start,
        split.poses[trajectory, start],
        velocities[trajectory, start],
        truth,
        phase,
        airborne,
        length,
        dataset.widths(),
    )


def residual_vectors(segments: Segments, predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position residual over half the width (as in eq. 1) and rotation vector (rad), world frame, each
    [..., M, L, K, 3], of predicted poses [..., M, L, K, 7]: all a fit needs."""
    truth = segments.truth
    linear = (predicted[..., :3] - truth[..., :3]) / (segments.widths[:, None] / 2)
    angular = rotations.to_rotation_vector(rotations.multiply(predicted[..., 3:], rotations.conjugate(truth[..., 3:])))
    return linear, angular


def residual_parts(segments: Segments, predicted: np.ndarray) -> dict[str, np.ndarray]:
    """The residual broken down for locating it: the COMPONENTS [..., M, L, K] (world normal/tangential parts)
    and the rotation vector in the body frame, "body_angular" [..., M, L, K, 3]."""
    linear, angular = residual_vectors(segments, predicted)
    return {
        "body_angular": rotations.rotate(rotations.conjugate(segments.truth[..., 3:]), angular),
        "linear_normal": np.abs(linear[..., 2]),
        "linear_tangential": np.linalg.norm(linear[..., :2], axis=-1),
        "angular_normal": np.abs(angular[..., 2]),
        "angular_tangential": np.linalg.norm(angular[..., :2], axis=-1),
    }


class SegmentSimulator:
    """Residual vectors of many parameter sets on the same segments, all in one batched call of one engine (MuJoCo
    unless named: sim/engines.py)."""

    def __init__(
        self, dataset: Recordings, segments: Segments, nthread: int | None = None, engine_name: str = "mujoco"
    ):
        self.segments = segments
        self.engine_name = engine_name
        self.rollouts = engine(engine_name).rollouts(dataset, nthread)
        self._cache: OrderedDict[bytes, np.ndarray] = OrderedDict()  # parameter set's digest -> its residuals

    def close(self) -> None:
        """Release the engine's worker processes (stepped engines); MuJoCo's threads need nothing."""
        self.rollouts.close()

    def predict(self, params: list) -> tuple[np.ndarray, np.ndarray]:
        """Predicted poses [B, M, L, K, 7] and which items blew up [B, M]."""
        result = self.rollouts.simulate(params, self.segments.poses0, self.segments.velocities0, self.segments.length)
        return result.poses, result.unstable

    def residuals(self, params: list) -> np.ndarray:
        """[B, M, L, K, 6]: position residual over half the width, rotation residual (rad), per frame and body.

        A rollout is judged by where it goes, capped at UNSTABLE_RESIDUAL, which every frame from a divergence on
        scores: a segment that gains some energy (a soft contact pushing a resting body out of the floor) may still
        follow the recording, and scoring it as blown up once rejected a right centre-of-mass offset.

        A parameter set simulated before on these segments is not simulated again: every engine's rollout is a
        function of its parameters alone (the cache holds RESIDUAL_CACHE_BYTES)."""
        keys = [hashlib.sha256(pickle.dumps(p, protocol=pickle.HIGHEST_PROTOCOL)).digest() for p in params]
        asked = {key: p for key, p in zip(keys, params) if key not in self._cache}
        if asked:
            for key, residuals in zip(asked, self._simulate(list(asked.values()))):
                self._cache[key] = kept = residuals.copy()  # not a view keeping the whole batch alive
                kept.flags.writeable = False
        out = np.stack([self._cache[key] for key in keys])
        for key in keys:
            self._cache.move_to_end(key)
        capacity = max(len(keys), RESIDUAL_CACHE_BYTES // max(out[0].nbytes, 1))
        while len(self._cache) > capacity:
            self._cache.popitem(last=False)
        return out

    def _simulate(self, params: list) -> np.ndarray:
        poses, _ = self.predict(params)
        stacked = np.concatenate(residual_vectors(self.segments, poses), axis=-1)
        stacked = np.nan_to_num(stacked, nan=UNSTABLE_RESIDUAL, posinf=UNSTABLE_RESIDUAL, neginf=-UNSTABLE_RESIDUAL)
        return np.clip(stacked, -UNSTABLE_RESIDUAL, UNSTABLE_RESIDUAL)

    def trajectory_losses(self, entry_losses: np.ndarray, n_trajectories: int) -> np.ndarray:
        """Per-trajectory mean loss [..., N] from per-entry losses [..., M, L, K, 6]."""
        per_segment = entry_losses.sum(axis=-1).mean(axis=(-1, -2))  # [..., M]
        totals = np.zeros(per_segment.shape[:-1] + (n_trajectories,))
        counts = np.bincount(self.segments.trajectory, minlength=n_trajectories)
        np.add.at(totals.T, self.segments.trajectory, np.moveaxis(per_segment, -1, 0))
        return totals / np.maximum(counts, 1)
