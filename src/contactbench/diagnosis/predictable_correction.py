"""The predictability check's correction (predictable.py): a small MLP ensemble from the recorded states to a
generalized acceleration per body, integrated over each segment into a change of the base simulator's residuals, and
its training (each member stopped early on its own fold of the train tosses)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from contactbench.diagnosis.open_world import integration_matrix
from contactbench.diagnosis.predictable_states import Inputs
from contactbench.diagnosis.segments import UNSTABLE_RESIDUAL


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
