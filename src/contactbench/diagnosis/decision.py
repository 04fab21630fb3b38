"""When a candidate counts: the decision rule and the paired bootstrap it rests on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactbench.diagnosis.library import Effect


@dataclass(frozen=True)
class Decision:
    """When an effect counts: significantly better on val than the model of its round (paired bootstrap, 95%),
    practically meaningful, and a better BIC on train; then all of it again against that model refitted from the
    effect's own values (Diagnosis.refit_control). Meaningful: in the first round, closing at least `margin` of the
    base simulator's val loss; in a later round (and for each effect given the others), closing at least
    `later_margin` of the val loss of the model without it, a higher bar because the first effect's model-form error
    is a source of spurious gains of its own (measured against the base loss instead, a large first effect left true
    second effects below any usable margin), or with that much removed per free-flight segment (`flies`: a true wind
    beside a floor tilt closes little of the whole loss and most of the free-flight loss). The blind sets that set
    both margins: docs/results/calibration.md. An effect a model-free
    measurement already shows beyond that measurement's own margin (an apparent gravity or a drag in free flight) is
    practically meaningful by that measurement, and needs only the significance and the BIC; one it rules out is not
    meaningful, whatever it gains. The open-world correction (physics nobody listed) must close `margin` of the base
    val loss too: it leaves out the impacts and the contact normal, where two engines disagree with nothing concealed
    (diagnosis.open_world)."""

    margin: float = 0.05
    later_margin: float = 0.10
    confidence: float = 0.95

    @staticmethod
    def significant(effect: Effect, improvement: float, ci: list[float], airborne: dict | None = None) -> bool:
        """Significantly better on val than the reference model; or, for an effect free flight measures (a drag, an
        apparent gravity), significantly better on the val segments in free flight, where it acts and every engine
        integrates the same law, without a loss on the whole val by point estimate. On the whole val loss contact
        noise can swamp it: a drag beside a floor tilt removed a significant share of the free-flight loss and moved
        the whole val loss by an interval covering zero."""
        if ci[0] > 0:
            return True
        return bool(effect.measured and improvement > 0 and airborne is not None and airborne["ci95"][0] > 0)

    def meaningful(
        self, effect: Effect, first_round: bool, closes_of_base: float, improvement: float, airborne: dict | None = None
    ) -> bool:
        if effect.measured or effect.ruled_out:
            return effect.measured
        if first_round:
            return closes_of_base >= self.margin
        return improvement >= self.later_margin or self.flies(airborne)

    def flies(self, airborne: dict | None) -> bool:
        """Free-flight evidence for a later effect (Diagnosis.airborne_gain): significant on the val segments in which
        every body flies, and what it removes there per segment is at least `later_margin` of its round's model's mean
        loss per segment over all phases. In free flight every engine integrates the same law, so no contact
        model-form error is left there for a passenger to ride on; measured against the whole loss, because relative
        to a free flight that the round's model already fits, refitting its parameters "gains" nearly all of it."""
        return airborne is not None and airborne["ci95"][0] > 0 and airborne["removed_per_segment"] >= self.later_margin

    @staticmethod
    def may_rival(record: dict) -> bool:
        """Whether a fitted candidate of a round (its record) that does not pass could still be the physics behind
        what the best passing one gains, if val cannot tell the two apart: it improves val and lowers the BIC at a
        resolved value, free flight does not rule it out, and it was not refitted away (its refit control) or found
        no better than its special case."""
        return bool(
            record["val_improvement"] > 0
            and record["delta_bic"] < 0
            and not record["negligible"]
            and not record.get("ruled_out_model_free")
            and "refit_control" not in record
            and "no_better_than" not in record
        )


def bootstrap_ratio(
    base: np.ndarray, other: np.ndarray, draws: int, rng: np.random.Generator, confidence: float = 0.95
) -> tuple[float, list[float]]:
    """Relative improvement 1 - mean(other) / mean(base) over paired per-trajectory values, with a percentile
    interval from resampling trajectories."""
    base, other = np.asarray(base, float), np.asarray(other, float)
    point = 1.0 - other.mean() / base.mean()
    picks = rng.integers(0, len(base), size=(draws, len(base)))
    samples = 1.0 - other[picks].mean(axis=1) / base[picks].mean(axis=1)
    tail = (1.0 - confidence) / 2 * 100
    return float(point), [float(np.percentile(samples, tail)), float(np.percentile(samples, 100 - tail))]
