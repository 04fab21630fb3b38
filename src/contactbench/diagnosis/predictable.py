"""Whether a flexible correction of the fitted simulator predicts held-out residuals better than on null data.

Before the diagnosis says `none` (nothing is missing) it must show that what the fitted base simulator leaves is not
predictable from the recorded states. A small MLP maps each recorded state a segment passes through (its phase, the
velocity and its direction, the slip of the vertices on the floor, the spin, the impact speed of the lowest vertex,
height and orientation, the place on the floor) to a generalized acceleration per body, world frame; integrated over
the segment's frames as in diagnosis.open_world (frame j moves by dt^2 sum_{i<j} (j - i) a(x_i)), it corrects the
base simulator's short-horizon residual. Four members, each stopped early on its own quarter of the train tosses and
fitted on the rest, are averaged (fixed seeds, one thread: deterministic). On val and on test: the per-trajectory
robust loss the diagnosis scores with (ResidualFit.robust, trajectory_losses) before and after the correction, gain =
1 - after / before, with a bootstrap interval over trajectories (decision.bootstrap_ratio).

Two engines never agree exactly, so the correction gains on every dataset: on the nulls of the calibration 1-15% of
the base loss, most of it at impacts and along the contact normal (MuJoCo's soft contact and impact laws), and on
the shapes that tip over edges along the floor too. A single bound on the whole gain (0.18) passed 4 of the 13
concealed effects of the calibration and 6 of 18 held out. So what is judged is where and on what the gain rests
(STATISTICS): each part of the correction alone (free flight, impacts, the contact normal, the rest of contact); the
gain each group of recorded quantities carries, lost when that group is shuffled among the states of the same phase
(permutation importance); the gain lost when every state is turned about the vertical and its correction turned
back (a homogeneous floor under vertical gravity has no preferred heading); and the gain left with every group
shuffled (a constant per phase). Each has its own bound, the largest null interval plus a margin (NULL_GAIN_BOUNDS,
from benchmarks/predictable_calibration.py); the correction `passes` where a statistic's val and test intervals
both lie above its bound: 8 of those 13 effects and 13 of the 18, and no null of 27 (14 of them held out). Contact
feedback is left out, as in the open world: the correction says that something is missing, where and on what, not
what a MuJoCo model of it would be.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from contactbench import rotations
from contactbench.diagnosis.decision import bootstrap_ratio
from contactbench.diagnosis.open_world import integration_matrix
from contactbench.diagnosis.phases import (
    CONTACT_HEIGHT,
    FREE,
    IMPACT,
    PHASES,
    REST,
    ROLLING,
    SLIDING,
    label_phases,
    recorded_velocities,
)
from contactbench.diagnosis.segments import UNSTABLE_RESIDUAL, Segments
from contactbench.kinematics import world_vertices
from contactbench.scene import Recordings, Split

if TYPE_CHECKING:
    from contactbench.diagnosis.fitting import ResidualFit
    from contactbench.diagnosis.library import Hypothesis
    from contactbench.diagnosis.state import Diagnosis

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

# Parts of the correction, judged each against its own null bound: the accelerations at the states of some phases,
# on some outputs (0-2: linear x, y, z; 3-5: angular).
PARTS = {
    "free": ((FREE,), (0, 1, 2, 3, 4, 5)),
    "impact": ((IMPACT,), (0, 1, 2, 3, 4, 5)),
    "contact_normal": ((SLIDING, ROLLING, REST), (2,)),
    "contact_tangential": ((SLIDING, ROLLING, REST), (0, 1, 3, 4, 5)),
}
# What is judged against nulls: each part alone, the gain each feature group carries, and the gain left with every
# group shuffled (a constant per phase).
# Besides the groups: "heading", the gain lost when every state is turned about the vertical by a random angle and
# its correction turned back. A homogeneous floor under vertical gravity has no preferred heading, so a correction
# that needs the world's heading (a wind, a floor whose friction differs between x and y) gains more than one that
# turns with the state (friction along the slip, a Coriolis force); on nulls turning costs nothing (it even helps).
DEPENDENCES = (*GROUPS, "heading", "constant")
STATISTICS = (*PARTS, *DEPENDENCES)
# The bound each statistic must pass, on val and on test (the lower end of the 95% interval above it), before the
# correction counts as gaining more than with nothing missing: the largest upper end of that statistic's val and test
# intervals over 13 null datasets (nothing concealed: cubes of seeds 0-4, dodecahedra, octahedra and tetrahedra of
# seeds 0-1, an icosahedron and a truncated octahedron of seed 0; 60 train / 120 val / 110 test tosses, quick budget,
# Settings() as below), plus NULL_MARGIN; the null that set it in the comment. Measured by
# benchmarks/predictable_calibration.py with the base simulator of library.base_parameters as it stands (friction,
# floor stiffness and damping, the floor's solimp impedance); a change of the base simulator, of the features or of
# Settings needs a new calibration.
NULL_MARGIN = 0.01  # 1% of the base loss: beyond the null intervals' own width, room for shapes not measured
NULL_GAIN_BOUNDS = {
    "free": 0.025,  # octahedron seed 0: 0.015
    "impact": 0.137,  # tetrahedron seed 0: 0.126 (the engines' impact laws differ)
    "contact_normal": 0.088,  # tetrahedron seed 1: 0.077 (MuJoCo's soft contact sinks and lifts otherwise)
    "contact_tangential": 0.088,  # cube seed 3: 0.077
    "direction": 0.123,  # octahedron seed 0: 0.112
    "speed": 0.060,  # octahedron seed 0: 0.049
    "spin": 0.054,  # tetrahedron seed 0: 0.044
    "impact_speed": 0.035,  # tetrahedron seed 1: 0.024
    "height_orientation": 0.030,  # tetrahedron seed 0: 0.019
    "floor_position": 0.013,  # tetrahedron seed 1: 0.003 (a homogeneous floor: nothing to read from the place)
    "heading": 0.016,  # cube seed 3: 0.005 (the nulls' point values are all at or below 0)
    "constant": 0.082,  # tetrahedron seed 1: 0.071
}
STATISTIC_WORDS = {
    "free": "in free flight",
    "impact": "at impacts",
    "contact_normal": "along the floor normal in contact",
    "contact_tangential": "along the floor and in rotation in contact",
    "direction": "on the direction of motion and slip",
    "speed": "on the speed",
    "spin": "on the spin",
    "impact_speed": "on the impact speed",
    "height_orientation": "on the height and orientation",
    "floor_position": "on the position on the floor",
    "heading": "on the heading in the world (which way along the floor)",
    "constant": "as a constant per phase",
}


@dataclass(frozen=True)
class Settings:
    """The correction's size and training; the defaults are what the calibration measured."""

    hidden: int = 32
    layers: int = 2
    learning_rate: float = 3e-3
    weight_decay: float = 1e-4  # on the loss relative to the base simulator's
    max_steps: int = 600
    check_every: int = 5  # steps between early-stopping checks on the held-back train tosses
    patience: int = 60  # steps without a better held-back loss before a member stops
    folds: int = 4  # ensemble members, each stopped early on its own share of the train tosses
    permutations: int = 3  # repeats of each permutation (their mean gain is reported)
    seed: int = 0


# ---------------------------------------------------------------- inputs


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
        velocity[..., :2], spin[..., :2] = _turn(velocity[..., :2], angles), _turn(spin[..., :2], angles)
        return dataclasses.replace(self, velocity=velocity, spin=spin, slip=_turn(self.slip, angles))

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


def _turn(vectors: np.ndarray, angles: np.ndarray) -> np.ndarray:
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


# ---------------------------------------------------------------- the correction


class Member(torch.nn.Module):
    """Standardized recorded state -> acceleration per body (6 outputs, each in units of `unit`)."""

    def __init__(self, mean: np.ndarray, std: np.ndarray, unit: np.ndarray, hidden: int, layers: int):
        super().__init__()
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float64))
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float64))
        self.register_buffer("unit", torch.as_tensor(unit, dtype=torch.float64))  # [K, 6]
        width, blocks = len(mean), []
        for _ in range(layers):
            blocks += [torch.nn.Linear(width, hidden), torch.nn.SiLU()]
            width = hidden
        last = torch.nn.Linear(width, 6)
        # starts as no correction: a member stopped at its first check leaves the base simulator as it is
        torch.nn.init.zeros_(last.weight)
        torch.nn.init.zeros_(last.bias)
        self.net = torch.nn.Sequential(*blocks, last).double()

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """[M, L, K, 6] accelerations in residual units (half-widths, rad) per s^2."""
        return self.net((features - self.mean) / self.std) * self.unit


@dataclass
class Correction:
    """The mean acceleration of the ensemble's members, integrated over each segment into a change of its residuals."""

    members: list[Member]
    integration: np.ndarray  # [L, L] integration_matrix

    def accelerations(self, features: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            tensor = torch.as_tensor(features)
            return torch.stack([member(tensor) for member in self.members]).mean(dim=0).numpy()

    def change(self, features: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """[M, L, K, 6] the change of every residual entry; with `mask` (broadcast to [M, L, K, 6]), only the
        accelerations where it is True act (a part of the correction)."""
        accelerations = self.accelerations(features)
        if mask is not None:
            accelerations = accelerations * mask
        return integrate(self.integration, accelerations)


def integrate(integration: np.ndarray | torch.Tensor, accelerations):
    """[M, L, K, 6]: what accelerations at a segment's states [M, L, K, 6] change in its residuals."""
    if isinstance(accelerations, torch.Tensor):
        return torch.einsum("ri,mik...->mrk...", torch.as_tensor(integration), accelerations)
    return np.einsum("ri,mik...->mrk...", integration, accelerations)


def corrected(residuals: np.ndarray, change: np.ndarray) -> np.ndarray:
    """Residuals with a correction's change applied; blown-up entries stay as they were (open_world.corrected)."""
    return np.where(np.abs(residuals) >= UNSTABLE_RESIDUAL, residuals, residuals + change)


def _robust(residuals: torch.Tensor, scale: float | None) -> torch.Tensor:
    """ResidualFit.robust in torch (the soft L1 the diagnosis scores with)."""
    if scale is None:
        return residuals**2
    return 2 * scale**2 * (torch.sqrt(1 + (residuals / scale) ** 2) - 1)


def output_units(residuals: np.ndarray, integration: np.ndarray) -> np.ndarray:
    """[K, 6] acceleration that a unit network output stands for: the constant acceleration that moves a segment's
    last frame by the residual's RMS there, so that every output starts on the scale of what it must explain."""
    reach = integration[-1].sum()  # displacement of the last frame per unit constant acceleration
    rms = np.sqrt(np.mean(residuals[:, -1] ** 2, axis=0))  # [K, 6]
    return np.maximum(rms, 1e-9) / reach


def train(train_inputs: Inputs, dt: float, settings: Settings = Settings()) -> tuple[Correction, dict]:
    """The correction fitted on train: `settings.folds` members, each fitted on all train tosses but one fold and
    stopped early on that fold (so the ensemble has seen every toss, and no member is stopped on what it fitted)."""
    torch.manual_seed(settings.seed)
    segments = train_inputs.fit.simulator.segments
    fold = np.random.default_rng(settings.seed).permutation(train_inputs.n_trajectories) % settings.folds
    if not train_inputs.usable.any():
        raise ValueError("no train segment whose base rollout stayed stable: nothing to fit a correction to")
    integration = integration_matrix(segments.length, dt)
    usable = train_inputs.usable
    states = train_inputs.features[usable].reshape(-1, train_inputs.features.shape[-1])
    mean, std = states.mean(axis=0), np.maximum(states.std(axis=0), 1e-6)
    unit = output_units(train_inputs.residuals[usable], integration)
    members, reports = [], []
    for held in range(settings.folds):
        checking = usable & (fold[segments.trajectory] == held)
        member = Member(mean, std, unit, settings.hidden, settings.layers)
        members.append(member)
        if checking.any() and (usable & ~checking).any():  # else it stays as it starts: no correction
            reports.append(_fit_member(member, train_inputs, usable & ~checking, checking, integration, settings))
    return Correction(members, integration), {
        "steps": [r["steps"] for r in reports],
        "best_steps": [r["best_step"] for r in reports],
        "held_back_gain": float(np.mean([r["held_back_gain"] for r in reports])) if reports else 0.0,
    }


def _fit_member(
    member: Member, train_inputs: Inputs, fitting: np.ndarray, checking: np.ndarray, integration, settings: Settings
) -> dict:
    """Full-batch Adam on the `fitting` segments, keeping the state with the least loss on the `checking` ones."""
    scale = train_inputs.fit.scale
    tensors = {
        name: (torch.as_tensor(train_inputs.features[rows]), torch.as_tensor(train_inputs.residuals[rows]))
        for name, rows in (("fit", fitting), ("check", checking))
    }
    # Each loss relative to the base simulator's on the same rows (1 before training: 1 - gain), so that the weight
    # decay means the same on every dataset; on the raw loss (~1e-4) it outweighed the data and stopped every fit.
    base_loss = {
        name: max(float(_robust(residuals, scale).sum(dim=-1).mean()), 1e-300)
        for name, (_, residuals) in tensors.items()
    }

    def loss(name: str) -> torch.Tensor:
        features, residuals = tensors[name]
        return _robust(residuals + integrate(integration, member(features)), scale).sum(dim=-1).mean() / base_loss[name]

    optimizer = torch.optim.Adam(member.parameters(), lr=settings.learning_rate, weight_decay=settings.weight_decay)
    best, best_step = 1.0, 0
    best_state = {key: value.clone() for key, value in member.state_dict().items()}
    for step in range(1, settings.max_steps + 1):
        optimizer.zero_grad()
        loss("fit").backward()
        optimizer.step()
        if step % settings.check_every:
            continue
        with torch.no_grad():
            held_loss = float(loss("check"))
        if held_loss < best:
            best, best_step = held_loss, step
            best_state = {key: value.clone() for key, value in member.state_dict().items()}
        elif step - best_step >= settings.patience:
            break
    member.load_state_dict(best_state)
    return {"steps": step, "best_step": best_step, "held_back_gain": 1.0 - best}


# ---------------------------------------------------------------- judging


def part_mask(states: States, part: str) -> np.ndarray:
    """[M, L, K, 6] where a part of the correction (PARTS) acts: its phases' states, its outputs."""
    phases, outputs = PARTS[part]
    return np.isin(states.phase, phases)[..., None] & np.isin(np.arange(6), outputs)


def gain(split_inputs: Inputs, residual_change: np.ndarray) -> float:
    """1 - after / before of the split's mean per-trajectory robust loss."""
    before = split_inputs.losses(split_inputs.residuals)
    after = split_inputs.losses(corrected(split_inputs.residuals, residual_change))
    return float(1 - after.mean() / before.mean())


def phase_shares(correction: Correction, val: Inputs) -> dict[str, float]:
    """Share of the val loss the correction closes that its accelerations at the states of each phase close alone
    (a phase whose part makes the loss worse counts nothing)."""
    return shares(
        {
            p: gain(val, correction.change(val.features, (val.states.phase == i)[..., None]))
            for i, p in enumerate(PHASES)
        }
    )


def cut(
    correction: Correction, split_inputs: Inputs, name: str, rng: np.random.Generator, mask: np.ndarray | None = None
) -> np.ndarray:
    """The correction's change of the residuals with one dependence (DEPENDENCES) cut: the group shuffled among the
    states of the same phase (States.permuted), or, for "heading", every state turned about the vertical by a random
    angle and its acceleration turned back."""
    if name != "heading":
        return correction.change(split_inputs.states.permuted(name, rng).features(), mask)
    angles = rng.uniform(0.0, 2 * np.pi, size=split_inputs.states.phase.shape)
    accelerations = correction.accelerations(split_inputs.states.turned(angles).features())
    for axes in (slice(0, 2), slice(3, 5)):  # linear and angular, along the floor
        accelerations[..., axes] = _turn(accelerations[..., axes], -angles)
    if mask is not None:
        accelerations = accelerations * mask
    return integrate(correction.integration, accelerations)


def carried(
    correction: Correction, val: Inputs, name: str, settings: Settings, mask: np.ndarray | None = None
) -> float:
    """The val gain a dependence carries: lost when it is cut (for "constant": kept with every group shuffled); of the
    accelerations where `mask` is True only, if given. Mean over `settings.permutations` cuts."""
    rng = np.random.default_rng(settings.seed)
    kept = float(np.mean([gain(val, cut(correction, val, name, rng, mask)) for _ in range(settings.permutations)]))
    return kept if name == "constant" else gain(val, correction.change(val.features, mask)) - kept


def shares(values: dict[str, float]) -> dict[str, float]:
    """Non-negative values as shares of their sum (all 0 where nothing is positive)."""
    clipped = {key: max(value, 0.0) for key, value in values.items()}
    total = sum(clipped.values())
    return {key: value / total if total > 0 else 0.0 for key, value in clipped.items()}


def excess(record: dict, name: str, bounds: dict[str, float] = NULL_GAIN_BOUNDS) -> float:
    """How far a statistic's lower interval end, the smaller of val's and test's, lies above its null bound."""
    return min(record[split]["statistics"][name]["ci95"][0] for split in ("val", "test")) - bounds[name]


def located(record: dict, correction: Correction, val: Inputs, settings: Settings) -> tuple[str, str, dict]:
    """Where (phase) and on what (group) the correction gains beyond nulls, and that group's gain by phase (shares).

    Where a group passes: the group furthest beyond its bound (the gain the engines' own differences leave, the
    direction of slip on an octahedron, is not what the excess depends on). Where only a part passes: the group that
    carries most of that part's gain. Where a part passes, the phase is that part's (of a contact part, the contact
    phase it closes most in), else where the group's gain acts most. Where nothing passes: the phase closing most and
    the group carrying most of the whole gain, to describe, not to decide."""
    groups = DEPENDENCES
    passing = [name for name in record["beyond_nulls"] if name in groups]
    parts = sorted((name for name in record["beyond_nulls"] if name in PARTS), key=lambda name: -excess(record, name))
    if passing:
        group = max(passing, key=lambda name: excess(record, name))
    elif parts:
        mask = part_mask(val.states, parts[0])
        group = max(groups, key=lambda name: carried(correction, val, name, settings, mask))
    else:
        group = max(record["dependence"], key=record["dependence"].get)
    by_phase = shares(
        {
            p: carried(correction, val, group, settings, (val.states.phase == index)[..., None])
            for index, p in enumerate(PHASES)
        }
    )
    if parts:
        phase = max((PHASES[p] for p in PARTS[parts[0]][0]), key=lambda p: record["phase_shares"][p])
    elif passing:
        phase = max(by_phase, key=by_phase.get)
    else:
        phase = max(record["phase_shares"], key=record["phase_shares"].get)
    return phase, group, by_phase


def judged(correction: Correction, split_inputs: Inputs, draws: int, confidence: float, settings: Settings) -> dict:
    """The correction's gain on one split (1 - after / before of the mean per-trajectory robust loss) with a bootstrap
    interval over trajectories, and the same for every statistic of STATISTICS: each part of the correction alone, the
    gain each dependence carries (lost when it is cut, cut(): the mean of `settings.permutations` cuts), and what is
    left with every group shuffled."""
    rng = np.random.default_rng(settings.seed)
    residuals, states = split_inputs.residuals, split_inputs.states
    before = split_inputs.losses(residuals)

    def after(change: np.ndarray) -> np.ndarray:
        return split_inputs.losses(corrected(residuals, change))

    full = after(correction.change(split_inputs.features))
    point, ci = bootstrap_ratio(before, full, draws, rng, confidence)
    statistics = {}
    for name in STATISTICS:
        if name in PARTS:
            other = after(correction.change(split_inputs.features, part_mask(states, name)))
        else:
            shuffled = np.mean(
                [after(cut(correction, split_inputs, name, rng)) for _ in range(settings.permutations)], axis=0
            )
            # a group's gain, (after shuffling - after) / before, is 1 - mean(other) / mean(before) for this other
            other = shuffled if name == "constant" else before - shuffled + full
        gained, interval = bootstrap_ratio(before, other, draws, rng, confidence)
        statistics[name] = {"gain": gained, "ci95": interval}
    return {"n_trajectories": int(split_inputs.n_trajectories), "gain": point, "ci95": ci, "statistics": statistics}


def check(steps: Diagnosis, hypothesis: Hypothesis, values: np.ndarray, settings: Settings = Settings()) -> dict:
    """The correction of a fitted hypothesis (usually the base simulator): fitted on train, its gain on val and test
    with 95% intervals (whole, by part, by feature group), where it acts, what it depends on, whether it gains more
    than on null data (`passes`), and a sentence for the report. The record:

    - val, test: gain and ci95 of the whole correction, and `statistics` (STATISTICS: gain, ci95 each);
    - beyond_nulls: the statistics above their NULL_GAIN_BOUNDS on val and test; passes: any;
    - phase, depends_on, depends_on_by_phase: where and on what (located());
    - phase_shares: share of the closed val loss by the phase of the states where the correction acts;
    - dependence: per group, its gain on val as a share of the whole (above 1 where shuffled states make the
      correction worse than none); "constant": the share kept with every group shuffled;
    - training, null_gain_bounds, sentence.

    Uses its own random generators (settings.seed), not steps.rng: running the check changes none of the pipeline's
    draws. About 3 s on one core at the quick budget (60 / 120 / 110 tosses)."""
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a few thousand small rows: a second thread costs more than it saves on shared cores
    try:
        dataset = steps.dataset
        valid = steps.train_split.valid_mask()
        origin = steps.train_split.poses[..., :2][valid].reshape(-1, 2).mean(axis=0)
        train_inputs = inputs(dataset, steps.train_split, steps.train_fit, hypothesis, values, origin)
        correction, training = train(train_inputs, dataset.dt, settings)
        test_split, test_fit = steps.test_segments()
        val = inputs(dataset, steps.val_split, steps.val_fit, hypothesis, values, origin)
        test = inputs(dataset, test_split, test_fit, hypothesis, values, origin)
        draws, confidence = steps.budget.bootstrap, steps.decision.confidence
        record: dict = {
            "training": training,
            "val": judged(correction, val, draws, confidence, settings),
            "test": judged(correction, test, draws, confidence, settings),
            "phase_shares": phase_shares(correction, val),
        }
        full = record["val"]["gain"]
        record["dependence"] = {
            group: max(record["val"]["statistics"][group]["gain"] / full, 0.0) if full > 0 else 0.0
            for group in DEPENDENCES
        }
        record["null_gain_bounds"] = dict(NULL_GAIN_BOUNDS)
        record["beyond_nulls"] = beyond_nulls(record)
        record["passes"] = bool(record["beyond_nulls"])
        record["phase"], record["depends_on"], record["depends_on_by_phase"] = located(
            record, correction, val, settings
        )
        record["sentence"] = sentence(record)
        return record
    finally:
        torch.set_num_threads(torch_threads)


def beyond_nulls(record: dict, bounds: dict[str, float] = NULL_GAIN_BOUNDS) -> list[str]:
    """The statistics in which the correction gains more than on any null: both the val and the test interval above
    the statistic's bound."""
    return [name for name in bounds if excess(record, name, bounds) > 0]


def sentence(record: dict) -> str:
    """One line for the report: how much the correction closes on test, and, where that is more than on nulls, where
    and on what."""
    test = record["test"]
    head = (
        f"A flexible correction of the fitted simulator closes {test['gain']:.0%} of its short-horizon test loss "
        f"[{test['ci95'][0]:.0%}, {test['ci95'][1]:.0%}]"
    )
    if not record["beyond_nulls"]:
        return head + ", no more than on null data: nothing predictable is missing."
    phase, group = record["phase"], record["depends_on"]
    share = f"{record['dependence'][group]:.0%} of its gain"
    what = (
        f"it is mostly a constant per phase ({share} kept with every recorded quantity shuffled)"
        if group == "constant"
        else f"it depends most {STATISTIC_WORDS[group]} ({share} lost without it)"
    )
    return (
        f"{head}, more than on null data ({', '.join(STATISTIC_WORDS[name] for name in record['beyond_nulls'])}): "
        f"most of it at {phase} states, and {what}."
    )


def calibration_table(results: dict[str, dict]) -> str:
    """A markdown table of check records by dataset name (benchmarks/predictable_calibration.py): each gain as val /
    test, with the lower ends of their 95% intervals."""

    def pair(val: dict, test: dict) -> str:
        return f"{val['gain']:.3f} ({val['ci95'][0]:.3f}) / {test['gain']:.3f} ({test['ci95'][0]:.3f})"

    lines = [
        "| dataset | whole | " + " | ".join(STATISTICS) + " | phase | top dependence | beyond nulls | s |",
        "|---" * (7 + len(STATISTICS)) + "|",
    ]
    for name, record in results.items():
        val, test = record["val"], record["test"]
        cells = " | ".join(pair(val["statistics"][s], test["statistics"][s]) for s in STATISTICS)
        lines.append(
            f"| {name} | {pair(val, test)} | {cells} "
            f"| {record['phase']} {record['phase_shares'][record['phase']]:.0%} "
            f"| {record['depends_on']} {record['dependence'][record['depends_on']]:.0%} "
            f"| {', '.join(record['beyond_nulls']) or '-'} | {record.get('check_s', float('nan')):.1f} |"
        )
    return "\n".join(lines)
