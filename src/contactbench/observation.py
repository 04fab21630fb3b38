"""How a dataset is observed: tracking noise on every pose and a lower frame rate, applied to any recordings.

The physics is never regenerated: an observation is a deterministic function of the recordings and a seed.
* `frame_stride = n` keeps frames 0, n, 2n, ... of every trajectory; dt becomes n dt.
* `noise_mm = s` adds Gaussian noise of s mm to every coordinate of every recorded position, and turns every
  orientation by a rotation vector with Gaussian components of s / (half the body's width) rad — the angle that
  moves a point at the body's half-width by about s. Recorded velocities are then dropped (a tracker does not
  measure them): models see velocities fitted to the noisy poses (`kinematics.fit_velocities`).
Noise is drawn per split from numpy's generator seeded with (seed, the split's name), so the same settings give the
same bytes. Scores are against the clean recording at the same frame rate where the recordings are synthetic, and
against the observed one where they are real (no clean one exists); metrics.json says which.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, replace

import numpy as np

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.scene import Recordings, Split


@dataclass(frozen=True)
class Observation:
    noise_mm: float = 0.0
    frame_stride: int = 1
    seed: int = 0

    def __post_init__(self):
        if isinstance(self.frame_stride, bool) or not isinstance(self.frame_stride, int) or self.frame_stride < 1:
            raise ContactbenchError(f"observation.frame_stride is {self.frame_stride!r} (expected a positive integer)")
        if isinstance(self.noise_mm, bool) or not isinstance(self.noise_mm, (int, float)) or not self.noise_mm >= 0:
            raise ContactbenchError(f"observation.noise_mm is {self.noise_mm!r} (expected a number >= 0, in mm)")

    @classmethod
    def of(cls, node) -> Observation:
        """From a config's `observation` node (none: the recordings as they are); checked as it is built."""
        node = node or {}
        return cls(node.get("noise_mm", 0.0), node.get("frame_stride", 1), node.get("seed", 0))

    @property
    def plain(self) -> bool:
        """The recordings as they are (no noise, every frame)."""
        return self.noise_mm == 0 and self.frame_stride == 1

    def describe(self, scored_against: str) -> dict:
        return {"noise_mm": float(self.noise_mm), "frame_stride": self.frame_stride, "scored_against": scored_against}

    def clean(self, dataset: Recordings) -> Recordings:
        """The recordings at the observed frame rate, without noise: what a synthetic dataset is scored against."""
        if self.frame_stride == 1:
            return dataset
        meta = {**dataset.meta, "dt": dataset.dt * self.frame_stride}
        thinned = {name: split.every(self.frame_stride) for name, split in dataset.splits.items()}
        return replace(dataset, meta=meta, splits=thinned)

    def observe(self, dataset: Recordings) -> Recordings:
        """What the models see: `clean` plus the noise."""
        thinned = self.clean(dataset)
        if self.noise_mm == 0:
            return thinned
        noisy = {name: self._noisy(name, split, thinned) for name, split in thinned.splits.items()}
        return replace(thinned, splits=noisy)

    def _noisy(self, name: str, split: Split, dataset: Recordings) -> Split:
        rng = np.random.default_rng([int(self.seed), zlib.crc32(name.encode())])
        sigma = self.noise_mm / 1000.0
        half_widths = dataset.widths() / 2
        position_noise = rng.normal(0.0, sigma, split.poses[..., :3].shape)
        rotation_noise = rng.normal(0.0, 1.0, split.poses[..., :3].shape) * (sigma / half_widths)[:, None]
        valid = split.valid_mask()[..., None, None]
        poses = split.poses.copy()
        poses[..., :3] += np.where(valid, position_noise, 0.0)
        turned = rotations.multiply(rotations.from_rotation_vector(rotation_noise), poses[..., 3:])
        poses[..., 3:] = np.where(valid, turned, poses[..., 3:])
        return Split(poses, split.lengths, None, dict(split.extras))
