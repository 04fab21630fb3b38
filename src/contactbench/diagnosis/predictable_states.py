"""What the predictability check (predictable.py) reads of the recordings: the recorded states a split's segments pass
through, as the physical quantities its correction may depend on (States, in feature groups), the ways of cutting a
group from them (shuffled among states of the same phase, or every state turned about the vertical), and one split's
segments with their base residuals (Inputs)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from contactbench import rotations
from contactbench.diagnosis.phases import CONTACT_HEIGHT, PHASES, label_phases, recorded_velocities
from contactbench.diagnosis.segments import UNSTABLE_RESIDUAL, Segments
from contactbench.kinematics import world_vertices
from contactbench.scene import Recordings, Split

if TYPE_CHECKING:
    from contactbench.diagnosis.fitting import ResidualFit
    from contactbench.diagnosis.library import Hypothesis

# What a correction may depend on, in groups whose share of the gain is reported (judged, States.permuted); the phase
# is the "where" and is never shuffled.
GROUPS = ("direction", "speed", "spin", "impact_speed", "height_orientation", "floor_position")
FEATURES = (
    "v_x",
    "v_y",
    "v_z",
    "speed",
    "slip_x",
    "slip_y",
    "slip_speed",
    "w_x",
    "w_y",
    "w_z",
    "spin",
    "lowest_v_z",
    "approach_speed",
    "height",
    "clearance",
    "up_body_x",
    "up_body_y",
    "up_body_z",
    "x",
    "y",
    *(f"phase_{p}" for p in PHASES),
)


@dataclass
class States:
    """The recorded states a split's segments pass through (frames start .. start + L - 1), per body, as the physical
    quantities the features are made of; each array [M, L, K, ...]."""

    velocity: np.ndarray  # [..., 3] m/s, world frame
    spin: np.ndarray  # [..., 3] rad/s, world frame
    slip: np.ndarray  # [..., 2] m/s: mean velocity along the floor of the vertices that touch it; 0 off the floor
    lowest_v_z: np.ndarray  # m/s: vertical velocity of the lowest vertex (negative: approaching the floor)
    height: np.ndarray  # of the body's origin above the recorded floor, in body widths
    clearance: np.ndarray  # of the lowest vertex, in body widths
    up: np.ndarray  # [..., 3] the world's vertical in the body frame: the orientation relative to the floor
    place: np.ndarray  # [..., 2] m, x and y relative to the train tosses' mean
    phase: np.ndarray  # phase codes (PHASES)

    def features(self) -> np.ndarray:
        """[M, L, K, F] in the order of FEATURES."""
        columns = [
            self.velocity,
            np.linalg.norm(self.velocity, axis=-1, keepdims=True),
            self.slip,
            np.linalg.norm(self.slip, axis=-1, keepdims=True),
            self.spin,
            np.linalg.norm(self.spin, axis=-1, keepdims=True),
            self.lowest_v_z[..., None],
            np.maximum(-self.lowest_v_z, 0.0)[..., None],
            self.height[..., None],
            self.clearance[..., None],
            self.up,
            self.place,
            (self.phase[..., None] == np.arange(len(PHASES))).astype(float),
        ]
        return np.nan_to_num(np.concatenate(columns, axis=-1))

    def turned(self, angles: np.ndarray) -> States:
        """The states turned about the vertical by `angles` [M, L, K] (rad): velocity, spin and slip along the floor.
        What the body frame sees (the world's vertical in it) and the place on the floor stay."""
        velocity, spin = self.velocity.copy(), self.spin.copy()
        velocity[..., :2], spin[..., :2] = turn(velocity[..., :2], angles), turn(spin[..., :2], angles)
        return dataclasses.replace(self, velocity=velocity, spin=spin, slip=turn(self.slip, angles))

    def permuted(self, group: str, rng: np.random.Generator) -> States:
        """The states with one group's quantities (GROUPS, or "constant": all of them, each from its own donor) taken
        from other states of the same phase and body: a shuffle that keeps where each state is, and cuts what the
        correction could read from that group. Direction and speed split each velocity into its horizontal heading
        and its size, so that the one can be shuffled without the other."""
        if group == "constant":
            out = self
            for each in GROUPS:
                out = out.permuted(each, rng)
            return out
        donor = _donors(self.phase, rng)  # flat index of each state's donor

        def take(values: np.ndarray) -> np.ndarray:
            flat = values.reshape(-1, *values.shape[self.phase.ndim :])
            return flat[donor].reshape(values.shape)

        changes: dict[str, np.ndarray] = {}
        if group == "direction":
            changes["velocity"] = self.velocity.copy()
            changes["velocity"][..., :2] = _with_heading(self.velocity[..., :2], take(self.velocity[..., :2]))
            changes["slip"] = _with_heading(self.slip, take(self.slip))
        elif group == "speed":
            changes["velocity"] = _with_size(self.velocity, take(self.velocity))
            changes["slip"] = _with_size(self.slip, take(self.slip))
        elif group == "spin":
            changes["spin"] = take(self.spin)
        elif group == "impact_speed":
            changes["lowest_v_z"] = take(self.lowest_v_z)
        elif group == "height_orientation":
            changes = {name: take(getattr(self, name)) for name in ("height", "clearance", "up")}
        elif group == "floor_position":
            changes["place"] = take(self.place)
        else:
            raise ValueError(f"unknown feature group {group!r}; known: {', '.join(GROUPS)}, constant")
        return dataclasses.replace(self, **changes)


def _donors(phase: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """For every state (flat index), another state of the same phase and body, drawn by a random permutation."""
    flat = phase.reshape(-1)
    body = np.broadcast_to(np.arange(phase.shape[-1]), phase.shape).reshape(-1)
    donor = np.arange(flat.size)
    for key in np.unique(flat.astype(np.int64) * phase.shape[-1] + body):
        rows = np.flatnonzero(flat.astype(np.int64) * phase.shape[-1] + body == key)
        donor[rows] = rng.permutation(rows)
    return donor


def turn(vectors: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Vectors along the floor [..., 2] turned counter-clockwise by `angles` [...]."""
    cos, sin = np.cos(angles), np.sin(angles)
    return np.stack([cos * vectors[..., 0] - sin * vectors[..., 1], sin * vectors[..., 0] + cos * vectors[..., 1]], -1)


def _with_heading(vectors: np.ndarray, donors: np.ndarray) -> np.ndarray:
    """Horizontal vectors [..., 2] turned to the donors' heading, their size kept (a donor at rest gives none)."""
    size = np.linalg.norm(vectors, axis=-1, keepdims=True)
    donor_size = np.linalg.norm(donors, axis=-1, keepdims=True)
    return size * np.where(donor_size > 0, donors / np.maximum(donor_size, 1e-300), 0.0)


def _with_size(vectors: np.ndarray, donors: np.ndarray) -> np.ndarray:
    """Vectors [..., D] scaled to the donors' size, their direction kept."""
    size = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return vectors * np.linalg.norm(donors, axis=-1, keepdims=True) / np.maximum(size, 1e-300)


def recorded_states(dataset: Recordings, split: Split, segments: Segments, origin: np.ndarray) -> States:
    """The recorded states the split's segments pass through (frames start .. start + L - 1)."""
    velocities_all = recorded_velocities(split, dataset.dt)
    phases_all = label_phases(dataset, split)
    frames = segments.start[:, None] + np.arange(segments.length)[None, :]
    rows = segments.trajectory[:, None]
    parts: dict[str, list[np.ndarray]] = {field.name: [] for field in dataclasses.fields(States)}
    for k in range(dataset.n_bodies):
        poses = np.nan_to_num(split.poses[rows, frames, k])  # [M, L, 7]
        velocity = np.nan_to_num(velocities_all[rows, frames, k])
        v, w = velocity[..., :3], velocity[..., 3:]
        width = float(dataset.widths()[k])
        vertices = world_vertices(poses, dataset.body_mesh(k).vertices)  # [M, L, V, 3]
        heights = vertices[..., 2] - dataset.floor_z
        lowest = heights.min(axis=-1)
        # the vertices that carry the contact, as diagnosis.phases.label_phases takes them
        touching = heights < lowest[..., None] + CONTACT_HEIGHT * width
        vertex_velocity = v[..., None, :] + np.cross(w[..., None, :], vertices - poses[..., None, :3])
        slip = (vertex_velocity[..., :2] * touching[..., None]).sum(axis=-2) / touching.sum(axis=-1)[..., None]
        parts["velocity"].append(v)
        parts["spin"].append(w)
        parts["slip"].append(np.where((lowest < CONTACT_HEIGHT * width)[..., None], slip, 0.0))
        parts["lowest_v_z"].append(
            np.take_along_axis(vertex_velocity[..., 2], heights.argmin(axis=-1)[..., None], axis=-1)[..., 0]
        )
        parts["height"].append((poses[..., 2] - dataset.floor_z) / width)
        parts["clearance"].append(lowest / width)
        parts["up"].append(
            rotations.rotate(rotations.conjugate(poses[..., 3:]), np.broadcast_to([0.0, 0.0, 1.0], v.shape))
        )
        parts["place"].append(poses[..., :2] - origin)
        parts["phase"].append(phases_all[rows, frames, k])
    return States(**{name: np.stack(values, axis=2) for name, values in parts.items()})


@dataclass
class Inputs:
    """One split's segments: base residuals, recorded states, and what scores them."""

    residuals: np.ndarray  # [M, L, K, 6] base simulator minus recordings (half-widths, rad)
    states: States
    features: np.ndarray  # [M, L, K, F] of the states
    usable: np.ndarray  # [M] the base rollout did not blow up
    fit: ResidualFit
    n_trajectories: int

    def losses(self, residuals: np.ndarray) -> np.ndarray:
        """Per-trajectory mean robust loss [N] of residuals [M, L, K, 6]."""
        return self.fit.simulator.trajectory_losses(self.fit.robust(residuals), self.n_trajectories)


def inputs(
    dataset: Recordings, split: Split, fit: ResidualFit, hypothesis: Hypothesis, values: np.ndarray, origin
) -> Inputs:
    residuals = fit.residuals(hypothesis, values[None])[0]
    states = recorded_states(dataset, split, fit.simulator.segments, origin)
    usable = (np.abs(residuals) < UNSTABLE_RESIDUAL).all(axis=(1, 2, 3))
    return Inputs(residuals, states, states.features(), usable, fit, split.n_trajectories)
