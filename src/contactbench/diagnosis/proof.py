"""Step 4, prove: on the held-out test tosses, a name earns itself only where its model improves full rollouts."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from contactbench.diagnosis.decision import bootstrap_ratio
from contactbench.diagnosis.library import Hypothesis
from contactbench.evaluation.scoring import score_model
from contactbench.models.analytical import EngineContactModel

if TYPE_CHECKING:
    from contactbench.diagnosis.state import Diagnosis


def short_horizon(
    steps: Diagnosis,
    base: Hypothesis,
    base_values: np.ndarray,
    final: Hypothesis,
    final_values: np.ndarray,
    confidence: float,
) -> dict:
    """The val statistic on the test split: the final model's short-horizon loss against the base's, per test
    trajectory, paired (full rollouts from six frames are chaotic: on the real cube their interval is 2x as
    wide)."""
    split, fit = steps.test_segments()
    before, after = (
        fit.simulator.trajectory_losses(fit.robust(fit.residuals(h, v[None])[0]), split.n_trajectories)
        for h, v in ((base, base_values), (final, final_values))
    )
    improvement, ci = bootstrap_ratio(before, after, steps.budget.bootstrap, steps.rng, confidence)
    return {"improvement": improvement, "ci": ci}


def full_rollouts(steps: Diagnosis, hypothesis: Hypothesis, values: np.ndarray) -> dict:
    """Test-split scores of the paper's protocol (full rollouts from the context frames)."""
    model = EngineContactModel(
        name="+".join(("base",) + hypothesis.names),
        engine=hypothesis.engine,
        parameters=hypothesis.contact_parameters(values),
    )
    score = score_model(model, steps.dataset, "test", steps.context_frames, dataset_name=steps.dataset.name, variant="")
    return {
        "pos_err": score.metrics.per_trajectory["pos_err"],
        "rot_err_rad": score.metrics.per_trajectory["rot_err_rad"],
    }


def prove(
    steps: Diagnosis, base: Hypothesis, base_values: np.ndarray, final: Hypothesis, final_values: np.ndarray
) -> tuple[dict, dict, dict]:
    """The held-out section of the document, and the base's and the final model's test scores. The named effects are
    confirmed only where the paper's full rollouts from the context frames improve on the base's, their 95% interval
    (paired bootstrap over test tosses) above zero: what the benchmark scores is what a name must improve. The
    short-horizon loss the effects were chosen on is reported beside it, not as proof (blind sets named COM offsets,
    inertias and rolling friction that the short horizon confirmed and full rollouts predicted worse)."""
    budget, confidence = steps.budget, steps.decision.confidence
    before = full_rollouts(steps, base, base_values)
    after = full_rollouts(steps, final, final_values) if final.effects else before
    improvement, ci = bootstrap_ratio(before["pos_err"], after["pos_err"], budget.bootstrap, steps.rng, confidence)
    rot_improvement, rot_ci = bootstrap_ratio(
        before["rot_err_rad"], after["rot_err_rad"], budget.bootstrap, steps.rng, confidence
    )
    short = short_horizon(steps, base, base_values, final, final_values, confidence) if final.effects else None
    held = {
        "split": "test",
        "confirmed": bool(final.effects) and ci[0] > 0,
        "short_horizon": short,
        "n_trajectories": int(len(before["pos_err"])),
        "base": {"pos_err": float(before["pos_err"].mean()), "rot_err_rad": float(before["rot_err_rad"].mean())},
        "augmented": {"pos_err": float(after["pos_err"].mean()), "rot_err_rad": float(after["rot_err_rad"].mean())},
        "improvement": improvement,
        "ci95": ci,
        "rot_improvement": rot_improvement,
        "rot_ci95": rot_ci,
    }
    return held, before, after


def each_effect(steps: Diagnosis, final: Hypothesis, final_values: np.ndarray) -> tuple[Hypothesis, np.ndarray, list]:
    """With several named effects, each must improve the held-out full rollouts given the others (the model without
    it, the others' values kept; 95% interval above zero), or it is dropped before the proof: a blind plate's wind
    came with an inertia scale that compensated MuJoCo's fluid model's angular drag, which the generator's wind did
    not have. Where none passes alone, the effects explain the same motion and stand or fall together."""
    if len(final.effects) < 2:
        return final, final_values, []
    with_all = full_rollouts(steps, final, final_values)["pos_err"]
    records, kept = [], []
    for effect in final.effects:
        others = final.with_effects(tuple(e for e in final.effects if e is not effect))
        without = full_rollouts(steps, others, others.start(final, final_values))["pos_err"]
        improvement, ci = bootstrap_ratio(
            without, with_all, steps.budget.bootstrap, steps.rng, steps.decision.confidence
        )
        records.append({"name": effect.name, "improvement": improvement, "ci95": ci, "kept": ci[0] > 0})
        if ci[0] > 0:
            kept.append(effect)
    if not kept or len(kept) == len(final.effects):
        for record in records:
            record["kept"] = True
        return final, final_values, records
    reduced = final.with_effects(tuple(kept))
    return reduced, reduced.start(final, final_values), records
