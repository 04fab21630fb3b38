"""Physics nobody listed: a sparse, phase-gated force correction fitted to the short-horizon residuals (SINDy-style).

When no library effect passes, the question left is whether the simulator and the recordings still disagree in a
systematic way. The correction is a generalized acceleration per body, world frame,

    a_c(x) = sum over chosen terms of  xi * [phase(x) = p] * theta_f(x)

with theta from a dictionary of candidate dependences (constant, velocity, |v| v, spin, spin x velocity, height, place
on the floor) and p one of the contact phases. Evaluated at the recorded states of a segment, it moves the simulated
frame j by sum_{i<j} (j - i) dt^2 a_c(x_i): the corrected residual is linear in xi, so terms are chosen by forward
selection on train (least squares weighted as the diagnosis' robust loss weighs the base residuals, stopped by BIC)
and then judged like a library effect: significantly better on val (paired bootstrap), closing at least the margin
of the base loss, better BIC on train. Impacts, and the contact normal in contact phases, are outside the dictionary
(see fit_correction). Contact feedback is
left out (a correction that pushes a body into the floor moves it in the linearisation), so the correction says
where and on what the mismatch depends, not what a MuJoCo model of it would be; its held-out check is on test
segments, not full rollouts.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from contactbench.diagnosis.decision import bootstrap_ratio
from contactbench.diagnosis.fitting import ResidualFit
from contactbench.diagnosis.library import Hypothesis
from contactbench.diagnosis.phases import FREE, IMPACT, PHASES, label_phases, recorded_velocities
from contactbench.diagnosis.segments import UNSTABLE_RESIDUAL, Segments
from contactbench.scene import Recordings, Split

if TYPE_CHECKING:
    from contactbench.diagnosis.state import Diagnosis

log = logging.getLogger(__name__)

FEATURES = (
    "1",
    "v_x",
    "v_y",
    "v_z",
    "|v|v_x",
    "|v|v_y",
    "|v|v_z",
    "w_x",
    "w_y",
    "w_z",
    "(w×v)_x",
    "(w×v)_y",
    "(w×v)_z",
    "height",
    "x",
    "y",
)
OUTPUTS = ("linear_x", "linear_y", "linear_z", "angular_x", "angular_y", "angular_z")
NORMAL = OUTPUTS.index("linear_z")  # the floor's normal


@dataclass(frozen=True)
class Dictionary:
    """The integrated candidate columns of one set of segments: G[m, j, k, p, f], the displacement of frame j+1
    (in residual units: half-widths, rad) a unit acceleration theta_f gated to phase p would cause, per output kind."""

    linear: np.ndarray  # [M, L, K, P, F] for the linear outputs (divided by the half width)
    angular: np.ndarray  # [M, L, K, P, F] for the angular outputs (rad)

    def column(self, output: int, phase: int, feature: int) -> np.ndarray:
        """[M, L, K] displacement of output `output` per unit coefficient of the term."""
        return (self.linear if output < 3 else self.angular)[..., phase, feature]


def recorded_states(dataset: Recordings, split: Split, segments: Segments, origin: np.ndarray) -> tuple:
    """Features [M, L, K, F] and phases [M, L, K] of the recorded states a segment passes through (frames start ..
    start + L - 1)."""
    frames = segments.start[:, None] + np.arange(segments.length)[None, :]
    rows = segments.trajectory[:, None]
    poses = split.poses[rows, frames]  # [M, L, K, 7]
    velocities = recorded_velocities(split, dataset.dt)[rows, frames]
    phases = label_phases(dataset, split)[rows, frames]
    v, w = velocities[..., :3], velocities[..., 3:]
    speed = np.linalg.norm(v, axis=-1, keepdims=True)
    height = poses[..., 2:3] - dataset.floor_z
    place = poses[..., :2] - origin
    features = np.concatenate([np.ones_like(height), v, speed * v, w, np.cross(w, v), height, place], axis=-1)
    return np.nan_to_num(features), phases


def integration_matrix(length: int, dt: float) -> np.ndarray:
    """[L, L]: row r (frame r + 1 of the segment) from the accelerations at the states 0 .. r, semi-implicit Euler on
    the frame grid: dt^2 (r + 1 - i) for i <= r."""
    rows, states = np.meshgrid(np.arange(length), np.arange(length), indexing="ij")
    return dt**2 * np.where(states <= rows, rows + 1 - states, 0).astype(float)


def integrate(features: np.ndarray, phases: np.ndarray, dt: float, widths: np.ndarray) -> Dictionary:
    """G_j = dt^2 sum_{i<j} (j - i) theta_i per phase: the displacement after j frames under accelerations theta_i."""
    gated = features[..., None, :] * (phases[..., None, None] == np.arange(len(PHASES))[:, None])  # [M, L, K, P, F]
    displacement = np.einsum("ri,mikpf->mrkpf", integration_matrix(features.shape[1], dt), gated)
    return Dictionary(displacement / (widths[None, None, :, None, None] / 2), displacement)


@dataclass
class Correction:
    """Chosen terms (output, phase, feature) and their coefficients (m/s^2 or rad/s^2 per unit of the feature)."""

    terms: list[tuple[int, int, int]]
    coefficients: np.ndarray

    def displacement(self, dictionary: Dictionary) -> np.ndarray:
        """[M, L, K, 6] the correction's change of each residual entry."""
        shape = dictionary.linear.shape[:3]
        out = np.zeros((*shape, 6))
        for (output, phase, feature), xi in zip(self.terms, self.coefficients):
            out[..., output] += xi * dictionary.column(output, phase, feature)
        return out

    def restricted(self, phase: int) -> Correction:
        """The terms gated to one phase."""
        keep = [i for i, term in enumerate(self.terms) if term[1] == phase]
        return Correction([self.terms[i] for i in keep], self.coefficients[keep])

    def described(self) -> list[dict]:
        return [
            {
                "output": OUTPUTS[output],
                "phase": PHASES[phase],
                "depends_on": FEATURES[feature],
                "coefficient": float(xi),
            }
            for (output, phase, feature), xi in zip(self.terms, self.coefficients)
        ]


def fit_correction(
    dictionary: Dictionary,
    residuals: np.ndarray,
    robust_scale: float,
    max_terms: int,
    usable: np.ndarray,
) -> Correction:
    """Forward selection of terms on weighted least squares, stopped by BIC; weights from the robust loss.

    residuals [M, L, K, 6]; usable [M] (segments whose base rollout did not blow up)."""
    target = np.where(usable[:, None, None, None], -residuals, 0.0)
    weights = np.where(usable[:, None, None, None], 1.0 / np.sqrt(1 + (residuals / robust_scale) ** 2), 0.0)
    n_entries = int(usable.sum()) * int(np.prod(residuals.shape[1:]))
    n_phases, n_features = dictionary.linear.shape[-2:]
    # Impacts are left out: the engines' impact laws differ even with nothing concealed, and generic terms there
    # "explain" that model-form error on every null dataset. So is the normal force while in contact: MuJoCo's soft
    # contact sinks and lifts a resting or sliding body unlike PyBullet's (on the blind nulls, most of what the
    # correction closed was linear_z in contact phases, by terms in a constant and the height); that is the contact
    # stiffness (solref/solimp), not physics nobody listed.
    candidates = [
        (o, p, f)
        for o in range(6)
        for p in range(n_phases)
        if p != IMPACT and (o != NORMAL or p == FREE)
        for f in range(n_features)
    ]
    columns = {c: np.where(usable[:, None, None], dictionary.column(*c), 0.0) for c in candidates}
    # a term that never acts (a phase nobody visits) cannot be chosen
    candidates = [c for c in candidates if np.abs(columns[c]).max() > 0]
    # Outputs do not interact: each keeps its own weighted target, terms, fit and RSS, and a candidate is scored by
    # refitting its output alone.
    scaled = [np.sqrt(weights[..., o]).ravel() for o in range(6)]
    targets = [target[..., o].ravel() * scaled[o] for o in range(6)]
    rss = [float(targets[o] @ targets[o]) for o in range(6)]
    fits: list[dict] = [{} for _ in range(6)]  # per output: term -> coefficient
    chosen: list[tuple[int, int, int]] = []
    best_bic = n_entries * np.log(sum(rss) / n_entries)
    while len(chosen) < max_terms:
        best = None
        for candidate in candidates:
            output = candidate[0]
            if candidate in fits[output]:
                continue
            terms = [*fits[output], candidate]
            design = np.stack([columns[t].ravel() for t in terms], axis=1) * scaled[output][:, None]
            xi, *_ = np.linalg.lstsq(design, targets[output], rcond=None)
            left = targets[output] - design @ xi
            total = sum(rss) - rss[output] + float(left @ left)
            if best is None or total < best[0]:
                best = (total, candidate, dict(zip(terms, xi)), float(left @ left))
        if best is None:
            break
        total, candidate, fit, output_rss = best
        bic = n_entries * np.log(total / n_entries) + (len(chosen) + 1) * np.log(n_entries)
        if bic >= best_bic:
            break
        best_bic = bic
        chosen.append(candidate)
        fits[candidate[0]], rss[candidate[0]] = fit, output_rss
    return Correction(chosen, np.array([fits[term[0]][term] for term in chosen]))


def corrected(residuals: np.ndarray, correction: Correction, dictionary: Dictionary) -> np.ndarray:
    """Residuals with the correction applied; blown-up entries stay as they were."""
    out = residuals + correction.displacement(dictionary)
    return np.where(np.abs(residuals) >= UNSTABLE_RESIDUAL, residuals, out)


# ---------------------------------------------------------------- the step


def explain(steps: Diagnosis, hypothesis: Hypothesis, values: np.ndarray) -> dict:
    """The sparse phase-gated correction (diagnosis.open_world) fitted on train, judged on val like an effect,
    and checked once on the test split's segments."""
    valid = steps.train_split.valid_mask()
    origin = steps.train_split.poses[..., :2][valid].reshape(-1, 2).mean(axis=0)
    train = _inputs(steps, steps.train_fit, steps.train_split, hypothesis, values, origin)
    correction = fit_correction(
        train["dictionary"], train["residuals"], steps.train_fit.scale, steps.budget.open_world_terms, train["usable"]
    )
    record: dict = {"terms": correction.described(), "passes": False}
    if correction.terms:
        val = _inputs(steps, steps.val_fit, steps.val_split, hypothesis, values, origin)
        before, after = _losses(steps.val_fit, val, correction, steps.val_split.n_trajectories)
        improvement, ci = bootstrap_ratio(before, after, steps.budget.bootstrap, steps.rng, steps.decision.confidence)
        n_residuals = 6 * steps.train_fit.entries
        train_before, train_after = (
            float(losses.mean())
            for losses in _losses(steps.train_fit, train, correction, steps.train_split.n_trajectories)
        )
        delta_bic = n_residuals * np.log(train_after / train_before) + len(correction.terms) * np.log(n_residuals)
        margin = steps.decision.margin
        record.update(
            {
                "val_improvement": improvement,
                "ci95": ci,
                "delta_bic": float(delta_bic),
                "margin": margin,
                "passes": bool(ci[0] > 0 and improvement >= margin and delta_bic < 0),
                "located": _location(steps, val, correction),
            }
        )
        if record["passes"]:
            test_split, test_fit = steps.test_segments()
            test = _inputs(steps, test_fit, test_split, hypothesis, values, origin)
            before, after = _losses(test_fit, test, correction, test_split.n_trajectories)
            held, held_ci = bootstrap_ratio(before, after, steps.budget.bootstrap, steps.rng)
            record["heldout"] = {
                "split": "test",
                "what": "short-horizon segments (the correction is not a MuJoCo model, so no full rollouts)",
                "n_trajectories": int(test_split.n_trajectories),
                "improvement": held,
                "ci95": held_ci,
                "confirmed": held_ci[0] > 0,
            }
    log.info(
        "open world: %d terms, %s",
        len(correction.terms),
        "passes" if record["passes"] else "does not pass",
    )
    return record


def _inputs(steps: Diagnosis, fit: ResidualFit, split, hypothesis: Hypothesis, values: np.ndarray, origin) -> dict:
    residuals = fit.residuals(hypothesis, values[None])[0]
    features, phases = recorded_states(steps.dataset, split, fit.simulator.segments, origin)
    return {
        "residuals": residuals,
        "usable": (np.abs(residuals) < UNSTABLE_RESIDUAL).all(axis=(1, 2, 3)),
        "dictionary": integrate(features, phases, steps.dataset.dt, steps.dataset.widths()),
    }


def _location(steps: Diagnosis, inputs: dict, correction) -> dict:
    """Where the correction closes the val loss: the share its terms of each phase close alone, and the share of
    the closing per output component."""
    residuals = inputs["residuals"]
    usable = inputs["usable"][:, None, None, None]

    def gain(part) -> np.ndarray:  # [M, L, K, 6] loss closed by a correction
        after = corrected(residuals, part, inputs["dictionary"])
        return np.where(usable, steps.val_fit.robust(residuals) - steps.val_fit.robust(after), 0.0)

    by_phase = np.array([gain(correction.restricted(p)).sum() for p in range(len(PHASES))])
    by_output = gain(correction).sum(axis=(0, 1, 2))
    return {
        "phase_shares": {p: float(by_phase[i] / max(by_phase.sum(), 1e-300)) for i, p in enumerate(PHASES)},
        "output_shares": {o: float(by_output[i] / max(by_output.sum(), 1e-300)) for i, o in enumerate(OUTPUTS)},
        "phase": PHASES[int(np.argmax(by_phase))],
        "output": OUTPUTS[int(np.argmax(by_output))],
    }


def _losses(fit: ResidualFit, inputs: dict, correction, n_trajectories: int):
    """Per-trajectory robust loss of the base residuals and of the corrected ones."""
    residuals = inputs["residuals"]
    after = corrected(residuals, correction, inputs["dictionary"])
    return (
        fit.simulator.trajectory_losses(fit.robust(residuals), n_trajectories),
        fit.simulator.trajectory_losses(fit.robust(after), n_trajectories),
    )
