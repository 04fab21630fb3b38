"""Step 2, name: greedy forward selection of library effects on val, each judged by the decision rule."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from contactbench.diagnosis.decision import bootstrap_ratio
from contactbench.diagnosis.library import Effect, Hypothesis

if TYPE_CHECKING:
    from contactbench.diagnosis.state import Diagnosis

log = logging.getLogger(__name__)

# general effect -> the library effect it contains as a special case
SPECIAL_CASES = {"wind": "air_drag"}
# Mean short-horizon loss (squared half-widths) below which free flight is simulated exactly as recorded, up to
# rounding (a micrometre-scale residual): relative gains there are rounding, not physics.
EXACT_FLIGHT_LOSS = 1e-12
MIN_FLYING_TRAJECTORIES = 10  # val tosses with free-flight segments that free-flight evidence needs


@dataclass
class Naming:
    """What naming found: the model named on val, every candidate's record, the effects the first round could not
    tell apart (confounded: none is named), and each of several named effects judged given the others."""

    hypothesis: Hypothesis
    values: np.ndarray
    candidates: list[dict]
    confounded: list[str] = field(default_factory=list)
    given_the_others: list[dict] = field(default_factory=list)


def name_effects(steps: Diagnosis, base: Hypothesis, base_values: np.ndarray) -> Naming:
    """Greedy forward selection over the library."""
    confounded: list[str] = []
    given_the_others: list[dict] = []
    current, values = base, base_values
    current_val = base_val = steps.val_losses(current, values)
    current_train = float(steps.train_fit.loss(current, values[None])[0])
    records: list[dict] = []
    for round_ in range(steps.budget.max_effects):
        # Not an effect already named, nor one named effect's special case (air_drag beside wind: a second fluid
        # density, which a measured drag would otherwise let pass on noise).
        inside = {SPECIAL_CASES.get(name) for name in current.names}
        remaining = [e for e in steps.library.values() if e.name not in current.names and e.name not in inside]
        if not remaining:
            break
        screened = []
        for effect in remaining:
            trial = current.with_effect(effect)
            screened.append((steps.train_fit.screen(trial, trial.start(current, values)), effect))
        screened.sort(key=lambda item: item[0])
        log.info(
            "screen (train loss after one step, current %.5f): %s",
            current_train,
            ", ".join(f"{e.name} {s:.5f}" for s, e in screened),
        )
        # The front runners by the screen, and every effect a model-free measurement speaks for (an apparent gravity
        # or a drag in free flight): its bar is that measurement, which the screen's train loss does not see.
        front = [item for rank, item in enumerate(screened) if rank < steps.budget.front_runners or item[1].measured]
        fitted = []
        for screened_loss, effect in front:
            trial = current.with_effect(effect)
            trial_values, train_loss = steps.train_fit.fit_effect(
                trial, trial.start(current, values), len(effect.parameters), steps.budget.lsq_iterations
            )
            val = steps.val_losses(trial, trial_values)
            record = {
                "name": effect.name,
                "round": round_ + 1,
                "screen_train_loss": screened_loss,
                "train_loss": train_loss,
                "parameters": trial.reported(trial_values)[effect.name],
            }
            record["negligible"] = effect.negligible(record["parameters"])
            if effect.in_flight and (round_ > 0 or effect.measured):
                record["airborne"] = airborne_gain(steps, current, values, trial, trial_values)
            record.update(judge(steps, effect, record, val, current_val, current_train, base_val))
            if record["passes"]:
                refit_control(steps, effect, record, current, trial, trial_values, val, current_train, base_val)
            if effect.measured:
                record["measured_model_free"] = True
            if effect.ruled_out:
                record["ruled_out_model_free"] = True
            records.append(record)
            fitted.append((record, trial, trial_values, val, train_loss))
            log.info(
                "  %s: val improvement %.3f [%.3f, %.3f], dBIC %.0f -> %s",
                effect.name,
                record["val_improvement"],
                *record["ci95"],
                record["delta_bic"],
                "passes" if record["passes"] else "no",
            )
        for screened_loss, effect in (item for item in screened if item not in front):
            records.append(
                {
                    "name": effect.name,
                    "round": round_ + 1,
                    "screen_train_loss": screened_loss,
                    "val_improvement": None,
                    "ci95": None,
                    "passes": False,
                    "screened_out": True,
                }
            )
        require_more_than_special_cases(steps, fitted)
        passing = [item for item in fitted if item[0]["passes"]]
        if not passing:
            break
        best = max(passing, key=lambda item: item[0]["val_improvement"])
        # The effects the val data cannot tell from the best: paired against it, trajectory by trajectory. Not
        # only passing ones: a rival may miss significance against the base and still fit val as well as the best
        # (a cube's true rolling friction, insignificant as cubes seldom roll, beside an inertia that passed and was
        # named). Free flight tells a tie apart where it measures one of them.
        tied = [
            item
            for item in fitted
            if item is best
            or (item[0]["passes"] or steps.decision.may_rival(item[0]))
            and bootstrap_ratio(best[3], item[3], steps.budget.bootstrap, steps.rng, steps.decision.confidence)[1][1]
            >= 0
        ]
        tied = [item for item in tied if steps.library[item[0]["name"]].measured] or tied
        chosen = min(tied, key=lambda item: (len(item[1].parameters), -item[0]["val_improvement"]))
        # The chosen one and each tied effect not inside it or around it (air_drag in wind)
        rivals = [chosen[0]["name"]] + [item[0]["name"] for item in tied if not _nested(item[1], chosen[1])]
        if len(rivals) > 1:  # the data cannot say which
            for item in tied:
                item[0]["confounded_with"] = [name for name in rivals if name != item[0]["name"]]
            if not current.effects:  # a tie in a later round adds nothing, the named effects stand
                confounded = sorted(rivals)
            break
        chosen[0]["chosen"] = True
        _, current, values, _, _ = chosen
        # Converge the chosen model before the next round, so that a further effect must explain what this one
        # cannot, not merely let the base parameters move on (a refit alone gains on its own).
        values, current_train = steps.train_fit.least_squares(current, values, steps.budget.lsq_iterations)
        current_val = steps.val_losses(current, values)
    if len(current.effects) > 1:
        current, values = drop_passengers(steps, current, values, current_val, base_val, records, given_the_others)
    return Naming(current, values, records, confounded, given_the_others)


def judge(
    steps: Diagnosis,
    effect: Effect,
    record: dict,
    val: np.ndarray,
    reference_val: np.ndarray,
    reference_train: float,
    base_val: np.ndarray,
) -> dict:
    """The decision rule for a fitted candidate (its `record`: train loss, negligible) against a reference model
    with `effect`'s parameters fewer: significance on val, the margin of the base loss, BIC on train."""
    improvement, ci = bootstrap_ratio(reference_val, val, steps.budget.bootstrap, steps.rng, steps.decision.confidence)
    n_residuals = 6 * steps.train_fit.entries
    delta_bic = n_residuals * np.log(record["train_loss"] / reference_train) + len(effect.parameters) * np.log(
        n_residuals
    )
    closes = float((reference_val.mean() - val.mean()) / base_val.mean())
    first_round = record["round"] == 1
    airborne = record.get("airborne")
    meaningful = (
        steps.decision.meaningful(effect, first_round, closes, improvement, airborne) and not record["negligible"]
    )
    return {
        "val_improvement": improvement,
        "ci95": ci,
        "closes_of_base_loss": closes,
        "closes_ci95": [float(c * reference_val.mean() / base_val.mean()) for c in ci],
        "delta_bic": float(delta_bic),
        "passes": bool(steps.decision.significant(effect, improvement, ci, airborne) and meaningful and delta_bic < 0),
    }


def refit_control(
    steps: Diagnosis,
    effect: Effect,
    record: dict,
    current: Hypothesis,
    trial: Hypothesis,
    trial_values: np.ndarray,
    val: np.ndarray,
    current_train: float,
    base_val: np.ndarray,
) -> None:
    """Judge a passing candidate again against the model without it, refitted from the candidate's own values of
    the shared parameters: what the effect gained by letting the base parameters move on is not the effect (null
    datasets named effects at physically null values that "closed" more than the margin this way)."""
    control_values, control_train = steps.train_fit.least_squares(
        current, current.start(trial, trial_values), steps.budget.lsq_iterations
    )
    if control_train >= current_train:
        return
    control_val = steps.val_losses(current, control_values)
    against_record = dict(record)
    if "airborne" in record:
        against_record["airborne"] = airborne_gain(steps, current, control_values, trial, trial_values)
    against = judge(steps, effect, against_record, val, control_val, control_train, base_val)
    if "airborne" in against_record:
        against["airborne"] = against_record["airborne"]
    record["refit_control"] = {"train_loss": control_train, **against}
    record["passes"] = against["passes"]
    log.info(
        "  %s against its refit control: %.3f [%.3f, %.3f]",
        effect.name,
        against["val_improvement"],
        *against["ci95"],
    )


def require_more_than_special_cases(steps: Diagnosis, fitted: list[tuple]) -> None:
    """A general effect passes only where it is significantly better (Decision.significant) than its own special
    case fitted in the same round: wind that gains nothing on air drag is air drag (an octahedron's true drag once
    passed as a slow wind, just over the margin where the drag alone fell just under it)."""
    by_name = {item[0]["name"]: item for item in fitted}
    for record, trial, trial_values, val, _ in fitted:
        special = by_name.get(SPECIAL_CASES.get(record["name"], ""))
        if record["passes"] and special is not None:
            effect = steps.library[record["name"]]
            improvement, ci = bootstrap_ratio(
                special[3], val, steps.budget.bootstrap, steps.rng, steps.decision.confidence
            )
            airborne = airborne_gain(steps, special[1], special[2], trial, trial_values) if effect.measured else None
            if not steps.decision.significant(effect, improvement, ci, airborne):
                record["passes"] = False
                record["no_better_than"] = special[0]["name"]


def drop_passengers(
    steps: Diagnosis,
    current: Hypothesis,
    values: np.ndarray,
    current_val: np.ndarray,
    base_val: np.ndarray,
    records: list,
    given_the_others: list[dict],
) -> tuple[Hypothesis, np.ndarray]:
    """Each effect must pass the rule given the others: refit without it, and drop it if the model with it is not
    significantly better on val by the later margin (a passenger that rode in on the first effect's model-form
    error). Each judgement is appended to `given_the_others`."""
    for effect in current.effects:
        others = current.with_effects(tuple(e for e in current.effects if e is not effect))
        other_values, _ = steps.train_fit.least_squares(
            others, others.start(current, values), steps.budget.lsq_iterations
        )
        other_val = steps.val_losses(others, other_values)
        improvement, ci = bootstrap_ratio(
            other_val, current_val, steps.budget.bootstrap, steps.rng, steps.decision.confidence
        )
        closes = float((other_val.mean() - current_val.mean()) / base_val.mean())
        negligible = effect.negligible(current.reported(values)[effect.name])
        airborne = airborne_gain(steps, others, other_values, current, values) if effect.in_flight else None
        meaningful = steps.decision.meaningful(effect, False, closes, improvement, airborne)
        kept = bool(steps.decision.significant(effect, improvement, ci, airborne) and meaningful and not negligible)
        given_the_others.append(
            {
                "name": effect.name,
                "val_improvement": improvement,
                "ci95": ci,
                "closes_of_base_loss": closes,
                "airborne": airborne,
                "passes": kept,
            }
        )
        log.info("  %s given the others: %.3f [%.3f, %.3f] -> %s", effect.name, improvement, *ci, kept)
        if not kept:
            for record in records:
                if record["name"] == effect.name and record.get("chosen"):
                    record["chosen"], record["dropped_as_passenger"] = False, True
            return others, other_values
    return current, values


def airborne_gain(
    steps: Diagnosis, reference: Hypothesis, reference_values: np.ndarray, hypothesis: Hypothesis, values: np.ndarray
) -> dict | None:
    """Val improvement of `hypothesis` over `reference` on the half-length val segments in which every body flies
    the whole segment, paired over the trajectories that have such segments, and what it removes there per segment
    as a share of the reference's mean loss per half-length segment over all phases (Decision.flies); None where
    too few tosses fly or the reference flies as recorded."""
    fit, n_trajectories = steps.half_segments(), steps.val_split.n_trajectories
    segments = fit.simulator.segments
    flying = segments.trajectory[segments.airborne]
    present = np.bincount(flying, minlength=n_trajectories) > 0
    if present.sum() < MIN_FLYING_TRAJECTORIES:
        return None
    before, after = (
        fit.robust(fit.residuals(h, v[None])[0]).sum(axis=-1).mean(axis=(-1, -2))  # per segment [M]
        for h, v in ((reference, reference_values), (hypothesis, values))
    )
    if not before[segments.airborne].mean() > EXACT_FLIGHT_LOSS:
        return None  # the reference flies as recorded: nothing to gain there
    per_trajectory = [
        np.bincount(flying, weights=loss[segments.airborne], minlength=n_trajectories)[present]
        for loss in (before, after)
    ]
    improvement, ci = bootstrap_ratio(*per_trajectory, steps.budget.bootstrap, steps.rng, steps.decision.confidence)
    if not np.isfinite([improvement, *ci]).all():  # resamples of tosses that all fly exactly
        return None
    share = float(before[segments.airborne].mean() / before.mean())
    return {"improvement": improvement, "ci95": ci, "removed_per_segment": improvement * share}


def _nested(hypothesis: Hypothesis, chosen: Hypothesis) -> bool:
    """Whether one hypothesis' last effect is a special case of the other's (air_drag is wind without wind)."""
    pair = {hypothesis.effects[-1].name, chosen.effects[-1].name}
    return len(pair) == 1 or any(pair == {general, special} for general, special in SPECIAL_CASES.items())
