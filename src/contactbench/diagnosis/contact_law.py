"""The contact law first: before anything is named, every engine the project has is identified on the same train
segments, the fits are compared on val, and what the others lose against the best is located by phase and confirmed
on the held-out test tosses (short horizon and the paper's full rollouts).

Two engines never agree exactly, and what one engine's contact law leaves unexplained in another's data (or in real
recordings) is model-form error, not missing physics: it is where spurious names ride and true ones drown. So the
first finding is which contact law fits, and by how much the others miss, phase by phase.

MuJoCo is the diagnosis' own base fit (pipeline.Diagnosis.fit_base: Table 2c plus the floor contacts' impedance, a
global search then least squares); every other engine searches its own identified dimensions (sim/engines.py, with a
hinged scene's articulation) by the same global search on the same robust loss, once per contact option (PyBullet's
rigid or compliant contact), on fewer train tosses and without least squares: the comparison favours MuJoCo, so an
engine that still beats it does so by at least the margin reported."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from contactbench.diagnosis.bases import engine_bases
from contactbench.diagnosis.decision import bootstrap_ratio
from contactbench.diagnosis.fitting import ResidualFit
from contactbench.diagnosis.library import Hypothesis
from contactbench.diagnosis.phases import PHASES
from contactbench.diagnosis.segments import Segments, SegmentSimulator, cut_segments
from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.evaluation.scoring import score_model
from contactbench.models.analytical import EngineContactModel
from contactbench.sim.engines import ENGINE_CLASSES, engine

if TYPE_CHECKING:
    from contactbench.diagnosis.state import Diagnosis

log = logging.getLogger(__name__)
# The contact laws compared, by default every engine the project has; MuJoCo always, as the library is modelled there
ENGINES = tuple(ENGINE_CLASSES)
# What each engine is, for the report
LAWS = {
    "mujoco": "MuJoCo's soft convex contact (solref/solimp impedance, pyramidal friction cone)",
    "bullet": "PyBullet's rigid contact with restitution, or its compliant contact (stiffness, damping)",
    "drake": "Drake's compliant point contact (Hunt-Crossley dissipation, regularised Coulomb friction)",
}


@dataclass
class Candidate:
    """One fitted contact law and its losses: per val (and test) trajectory, in total and by phase."""

    label: str
    engine: str
    hypothesis: Hypothesis  # the diagnosis' MuJoCo base, or an engine's (Hypothesis.base)
    values: np.ndarray
    train_loss: float
    seconds: float
    val: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [N_val, phases] robust loss by phase
    test: np.ndarray | None = None  # [N_test, phases]
    full: dict | None = None  # test full rollouts: per-trajectory pos_err, rot_err_rad


def phase_losses(fit: ResidualFit, hypothesis: Hypothesis, values: np.ndarray, n_trajectories: int) -> np.ndarray:
    """[N, phases]: each trajectory's mean robust loss per (segment, body), split by the phase the segment spends the
    body in; the phases sum to the trajectory's loss (SegmentSimulator.trajectory_losses, with one body)."""
    segments = fit.simulator.segments
    entry = fit.robust(fit.residuals(hypothesis, values[None])[0])  # [M, L, K, 6]
    per_item = entry.sum(axis=-1).mean(axis=1)  # [M, K]
    table = np.zeros((n_trajectories, len(PHASES)))
    for k in range(per_item.shape[1]):
        np.add.at(table, (segments.trajectory, segments.phase[:, k]), per_item[:, k])
    items = np.bincount(segments.trajectory, minlength=n_trajectories) * per_item.shape[1]
    return table / np.maximum(items, 1)[:, None]


def _fits(steps: Diagnosis, name: str, segments: list[Segments]) -> list[ResidualFit]:
    return [
        ResidualFit(SegmentSimulator(steps.dataset, s, engine_name=name), scale=steps.train_fit.scale) for s in segments
    ]


def check_engines(engines: tuple[str, ...]) -> None:
    """One line for a list of engines the comparison cannot take."""
    unknown = [name for name in engines if name not in ENGINE_CLASSES]
    if unknown or "mujoco" not in engines or len(set(engines)) != len(engines):
        raise ContactbenchError(
            f"engines={list(engines)}: expected distinct names among {', '.join(ENGINE_CLASSES)}, mujoco among them "
            "(the effect library is modelled in MuJoCo)"
        )


def fit_engines(
    steps: Diagnosis, mujoco: Hypothesis, mujoco_values: np.ndarray, engines: tuple[str, ...] = ENGINES
) -> tuple[list[Candidate], list[dict]]:
    """Every engine of `engines` identified on train and scored on val and test (the MuJoCo base as fitted by the
    diagnosis); the engines that refuse the scene, each with its one line."""
    budget, dataset = steps.budget, steps.dataset
    test_split, test_fit = steps.test_segments()
    candidates = [
        Candidate(
            "mujoco",
            "mujoco",
            mujoco,
            mujoco_values,
            float(steps.train_fit.loss(mujoco, mujoco_values[None])[0]),
            steps.timings.get("base_fit_s", 0.0),
            phase_losses(steps.val_fit, mujoco, mujoco_values, steps.val_split.n_trajectories),
            phase_losses(test_fit, mujoco, mujoco_values, test_split.n_trajectories),
        )
    ]
    skipped = []
    # The other engines' searches see the first law_trajectories of the diagnosis' own train tosses.
    law_split = steps.train_split.select(np.arange(min(budget.law_trajectories, steps.train_split.n_trajectories)))
    law_segments = cut_segments(dataset, law_split, budget.segment_frames)
    for name in engines:
        if name == "mujoco":
            continue
        try:
            engine(name).check_scene(dataset)
        except NotApplicable as refusal:
            skipped.append({"engine": name, "reason": str(refusal)})
            log.info("contact law: %s skipped: %s", name, refusal)
            continue
        fits = _fits(steps, name, [law_segments, steps.val_fit.simulator.segments, test_fit.simulator.segments])
        try:
            for option in engine_bases(name, dataset.n_bodies, len(dataset.joints)):
                started = time.perf_counter()
                base = Hypothesis(dataset.n_bodies, base=option)
                values = fits[0].global_search(base, budget.law_evaluations, budget.batch, steps.seed)
                values, _ = fits[0].least_squares(base, values, budget.lsq_iterations)
                candidates.append(
                    Candidate(
                        option.label,
                        name,
                        base,
                        values,
                        float(fits[0].loss(base, values[None])[0]),
                        time.perf_counter() - started,
                        phase_losses(fits[1], base, values, steps.val_split.n_trajectories),
                        phase_losses(fits[2], base, values, test_split.n_trajectories),
                    )
                )
                log.info(
                    "contact law: %s fitted in %.0f s, val loss %.5f",
                    option.label,
                    candidates[-1].seconds,
                    candidates[-1].val.sum(axis=1).mean(),
                )
        finally:
            for fit in fits:
                fit.simulator.close()
    return candidates, skipped


def full_rollouts(steps: Diagnosis, candidate: Candidate) -> dict:
    """Test-split scores of the paper's protocol (full rollouts from the context frames) of one fitted law."""
    model = EngineContactModel(
        name=candidate.label,
        engine=candidate.engine,
        parameters=candidate.hypothesis.contact_parameters(candidate.values),
    )
    score = score_model(model, steps.dataset, "test", steps.context_frames, dataset_name=steps.dataset.name, variant="")
    return {key: score.metrics.per_trajectory[key] for key in ("pos_err", "rot_err_rad")}


def _by_phase(other: np.ndarray, best: np.ndarray, steps: Diagnosis) -> dict:
    """What the best law removes of the other's loss in each phase, as a share of the other's whole loss, with a
    percentile interval from resampling trajectories (paired)."""
    draws, confidence = steps.budget.bootstrap, steps.decision.confidence
    picks = steps.rng.integers(0, len(other), size=(draws, len(other)))
    gap = other - best  # [N, phases]
    point = gap.sum(axis=0) / other.sum()
    samples = gap[picks].sum(axis=1) / other[picks].sum(axis=(1, 2))[:, None]
    tail = (1.0 - confidence) / 2 * 100
    low, high = np.percentile(samples, [tail, 100 - tail], axis=0)
    return {p: {"share": float(point[i]), "ci95": [float(low[i]), float(high[i])]} for i, p in enumerate(PHASES)}


def compare(
    steps: Diagnosis, mujoco: Hypothesis, mujoco_values: np.ndarray, engines: tuple[str, ...] = ENGINES
) -> tuple[dict, list[Candidate], dict[str, float]]:
    """The contact-law section of the document, the fitted laws from the best on val (lowest loss) down, and how long
    each fit took (s)."""
    started = time.perf_counter()
    candidates, skipped = fit_engines(steps, mujoco, mujoco_values, engines)
    ranked = sorted(candidates, key=lambda c: c.val.sum(axis=1).mean())
    best = ranked[0]
    draws, confidence = steps.budget.bootstrap, steps.decision.confidence
    best.full = full_rollouts(steps, best)
    laws = []
    for candidate in candidates:
        record = {
            "law": candidate.label,
            "engine": candidate.engine,
            "description": LAWS[candidate.engine],
            "parameters": candidate.hypothesis.reported(candidate.values)["base"],
            "train_loss": candidate.train_loss,
            "val_loss": float(candidate.val.sum(axis=1).mean()),
            "test_loss": float(candidate.test.sum(axis=1).mean()),
            "best": candidate is best,
        }
        if candidate is not best:
            candidate.full = full_rollouts(steps, candidate)
            val_gain, val_ci = bootstrap_ratio(
                candidate.val.sum(axis=1), best.val.sum(axis=1), draws, steps.rng, confidence
            )
            test_gain, test_ci = bootstrap_ratio(
                candidate.test.sum(axis=1), best.test.sum(axis=1), draws, steps.rng, confidence
            )
            full_gain, full_ci = bootstrap_ratio(
                candidate.full["pos_err"], best.full["pos_err"], draws, steps.rng, confidence
            )
            rot_gain, rot_ci = bootstrap_ratio(
                candidate.full["rot_err_rad"], best.full["rot_err_rad"], draws, steps.rng, confidence
            )
            record["against_best"] = {
                "val": {"improvement": val_gain, "ci95": val_ci, "by_phase": _by_phase(candidate.val, best.val, steps)},
                "test": {
                    "improvement": test_gain,
                    "ci95": test_ci,
                    "by_phase": _by_phase(candidate.test, best.test, steps),
                },
                "full_rollouts": {
                    "pos_improvement": full_gain,
                    "ci95": full_ci,
                    "rot_improvement": rot_gain,
                    "rot_ci95": rot_ci,
                },
                "confirmed": bool(test_ci[0] > 0 and full_ci[0] > 0),
            }
        record["full_rollouts"] = {key: float(np.mean(value)) for key, value in candidate.full.items()}
        laws.append(record)
    document = {
        "best": best.label,
        "best_engine": best.engine,
        "laws": laws,
        "engines": list(engines),
        "skipped": skipped,
        "finding": finding(laws),
        "budget": {"law_trajectories": steps.budget.law_trajectories, "law_evaluations": steps.budget.law_evaluations},
    }
    # Timings apart from the document, which is the same bytes for the same data and seed
    seconds = {fit_seconds_key(c.label): c.seconds for c in candidates if c.engine != "mujoco"}
    return document, ranked, seconds | {"contact_law_s": time.perf_counter() - started}


def fit_seconds_key(label: str) -> str:
    return f"contact_law_fit_s ({label})"


def finding(laws: list[dict]) -> str:
    """One sentence per law the best one beats with confirmation: how much of its loss, and where most of it is."""
    best = next(law for law in laws if law["best"])
    sentences = []
    for law in laws:
        against = law.get("against_best")
        if against is None:
            continue
        phases = against["val"]["by_phase"]
        where = max(phases, key=lambda p: phases[p]["share"])
        full = against["full_rollouts"]
        verdict = "confirmed on test" if against["confirmed"] else "not confirmed on test"
        sentences.append(
            f"{best['law']} closes {100 * against['val']['improvement']:.0f}% of {law['law']}'s val loss "
            f"(95% CI {100 * against['val']['ci95'][0]:.0f}% to {100 * against['val']['ci95'][1]:.0f}%), "
            f"{100 * phases[where]['share']:.0f} points of it at {where}; {verdict}: test full-rollout position "
            f"error {law['full_rollouts']['pos_err']:.4f} -> {best['full_rollouts']['pos_err']:.4f} widths "
            f"({100 * full['pos_improvement']:+.1f}%, 95% CI {100 * full['ci95'][0]:.1f}% to "
            f"{100 * full['ci95'][1]:.1f}%)"
        )
    return "; ".join(sentences) if sentences else f"{best['law']} is the only contact law that simulates this scene"
