"""Step 4, prove: the held-out test split scores the named model against the base (full rollouts, short horizon)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from contactbench.diagnosis.decision import bootstrap_ratio
from contactbench.diagnosis.library import Hypothesis
from contactbench.evaluation.scoring import score_model
from contactbench.models.analytical import MujocoContactModel

if TYPE_CHECKING:
    from contactbench.diagnosis.pipeline import Diagnosis


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
    model = MujocoContactModel(
        name="+".join(("base",) + hypothesis.names), parameters=hypothesis.contact_parameters(values)
    )
    score = score_model(model, steps.dataset, "test", steps.context_frames, dataset_name=steps.dataset.name, variant="")
    return {
        "pos_err": score.metrics.per_trajectory["pos_err"],
        "rot_err_rad": score.metrics.per_trajectory["rot_err_rad"],
    }
