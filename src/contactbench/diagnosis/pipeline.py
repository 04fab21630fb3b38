"""The diagnosis of a dataset, its steps in order: the model-free measurements and the base fit (diagnosis.state),
the contact law (contact_law.py), then locate, name, model what the library does not name and prove: each step a
module of functions of the shared state that returns what it found (locate.py, naming.py, open_world.py and
predictable.py, proof.py); this module runs them and writes the document."""

from __future__ import annotations

import logging
import time

from contactbench.diagnosis import (
    contact_law,
    locate,
    naming,
    open_world,
    predictable,
    proof,
    simulated_drag,
)
from contactbench.diagnosis.decision import Decision
from contactbench.diagnosis.free_flight import MEASURED
from contactbench.diagnosis.state import Budget, Diagnosis
from contactbench.scene import Recordings
from contactbench.sim.effects import EFFECT_NAMES
from contactbench.sim.engines import engine

log = logging.getLogger(__name__)


def _verdict(effects: list, confounded: list[str], unexplained: dict | None, confirmed: bool) -> str:
    """effect (named on val, and the held-out full rollouts confirm it), confounded (two effects the data cannot tell
    apart), unexplained (what the base misses is predictable and no name is proven: the open-world correction passes
    or a flexible predictor beats the base by more than on null data), unconfirmed (named on val, not confirmed on
    test, nothing predictable left), none."""
    if effects and confirmed:
        return "effect"
    if confounded:
        return "confounded"
    if unexplained is not None:
        return "unexplained"
    return "unconfirmed" if effects else "none"


# The contact signatures and the phase where each acts: those of physics outside the library, and those of a library
# effect (contact_signatures.SPEAKS_TO).
OUTSIDE_SIGNATURES = {"speed": "sliding", "position": "sliding", "bounce_speed": "impact", "bounce_position": "impact"}
LIBRARY_SIGNATURES = {"anisotropy": "sliding", "spin": "sliding", "rolling": "rolling"}


def _unexplained(open_world_record: dict, predictor: dict, contact: dict, candidates: tuple[str, ...]) -> dict | None:
    """Where the predictable mismatch is and who found it, or None where nothing predictable is left: the open-world
    correction, a flexible predictor beyond what it gains on nulls, or a contact signature measured model-free that no
    candidate named on val accounts for (physics outside the library, or a library effect whose MuJoCo model did not
    pass: a brick's floor friction larger along x than y, measured and confirmed on test, closed less than the margin
    of the base val loss as MuJoCo's anisotropy)."""
    if open_world_record["passes"]:
        return {"by": "open_world", "phase": open_world_record["located"]["phase"]}
    if predictor["passes"]:
        return {"by": "predictor", "phase": predictor["phase"], "depends_on": predictor["depends_on"]}
    signatures = contact["signatures"]
    measured = [name for name in OUTSIDE_SIGNATURES if signatures[name]["evidence"] == MEASURED]
    measured += [
        name
        for name in LIBRARY_SIGNATURES
        if signatures[name]["evidence"] == MEASURED and signatures[name]["speaks_to"] not in candidates
    ]
    if measured:
        phase = {**OUTSIDE_SIGNATURES, **LIBRARY_SIGNATURES}[measured[0]]
        return {"by": "contact_signatures", "phase": phase, "depends_on": measured}
    return None


def naming_base(ranked: list, modelled: dict[str, set], contact: dict) -> tuple:
    """The law names are fitted on, and the library effects the contact signatures measure model-free: the best law
    on val whose engine models every such effect, else the best that models any library effect. A law a little
    better on val cannot name a measured anisotropy its engine has no model of (Drake's point contact has none); the
    runner-up that models it can, and a signature the best base cannot express would otherwise be reported as
    unexplained physics."""
    signatures = contact["signatures"]
    measured = {
        signatures[name]["speaks_to"] for name in LIBRARY_SIGNATURES if signatures[name]["evidence"] == MEASURED
    }
    usable = [law for law in ranked if modelled[law.engine]]
    return next((law for law in usable if measured <= modelled[law.engine]), usable[0]), measured


def run_diagnosis(
    dataset: Recordings,
    budget: Budget | None = None,
    decision: Decision | None = None,
    *,
    seed: int = 0,
    context_frames: int = 6,
    engines: tuple[str, ...] = contact_law.ENGINES,
) -> tuple[dict, dict]:
    """The diagnosis document (diagnosis.json) and the arrays its report draws; `engines`: the contact laws compared
    (diagnosis.contact_law), MuJoCo among them."""
    started = time.perf_counter()
    budget, decision = budget or Budget(), decision or Decision()
    contact_law.check_engines(engines)
    steps = Diagnosis(dataset, budget, decision, seed=seed, context_frames=context_frames)
    falling = steps.free_flight
    log.info("%s", falling["sentence"])
    base, base_values = steps.fit_base()
    # The contact law first: every engine fitted alike, the best on val, what the others miss where, on test. Names
    # are then fitted on the best law whose engine models the library in this scene.
    law, ranked, law_seconds = contact_law.compare(steps, base, base_values, engines)
    steps.timings |= law_seconds
    log.info("contact law: %s", law["finding"])
    modelled = {c.engine: engine(c.engine).library_effects(dataset) for c in ranked}
    naming_law, measured = naming_base(ranked, modelled, steps.contact)
    if naming_law.engine != "mujoco":
        steps.use_engine(naming_law.engine, modelled[naming_law.engine])
        base, base_values = steps.fit_base(naming_law.hypothesis, naming_law.values)
    law["naming_base"] = naming_law.label
    if naming_law is not ranked[0]:
        law["naming_base_why"] = (
            f"the contact signatures measure {', '.join(sorted(measured))}, which {ranked[0].label} does not model"
            if measured
            else f"{ranked[0].label} models no library effect in this scene"
        )
    law["not_modelled_on_naming_base"] = sorted(set(EFFECT_NAMES) - modelled[naming_law.engine])
    located = locate.locate(steps, base, base_values)
    clock = time.perf_counter()
    naming_found = naming.name_effects(steps, base, base_values)
    steps.timings["naming_s"] = time.perf_counter() - clock
    final, final_values, candidates = naming_found.hypothesis, naming_found.values, naming_found.candidates
    named_on_val = final.names
    final, final_values, each_on_test = proof.each_effect(steps, final, final_values)
    held, before, after = proof.prove(steps, base, base_values, final, final_values)
    held["each_effect"] = each_on_test
    open_world_record = predictor = unexplained = None
    if not held["confirmed"] and not naming_found.confounded:
        # Nothing named is proven: before saying `none` (or leaving an unconfirmed name as the answer), is what the
        # model misses predictable? First the sparse correction (terms a person can read), then a flexible predictor;
        # both of the model named on val (the base where nothing was), so that what an unconfirmed candidate does
        # explain is not read as something missing besides it.
        clock = time.perf_counter()
        open_world_record = open_world.explain(steps, final, final_values)
        steps.timings["open_world_s"] = time.perf_counter() - clock
        predictor = predictable.check(steps, final, final_values)
        unexplained = _unexplained(open_world_record, predictor, steps.contact, named_on_val)
    effects = []
    for effect in final.effects:
        chosen = next(c for c in candidates if c["name"] == effect.name and c.get("chosen"))
        effects.append(
            {
                "name": effect.name,
                "parameters": final.reported(final_values)[effect.name],
                "ci95": chosen["ci95"],
                "val_improvement": chosen["val_improvement"],
                "physics": effect.physics,
                "mujoco": effect.mujoco,
            }
        )
        if effect.name == "air_drag" and final.engine == "mujoco" and "drag_ci95" in falling["splits"].get("val", {}):
            # wind is left out: free flight measures its drag in moving air, not the drag's size
            simulated = simulated_drag.drag_per_metre(dataset, final.contact_parameters(final_values), steps.rng)
            effects[-1]["against_free_flight"] = simulated_drag.against_free_flight(simulated, falling["splits"]["val"])
    document = {
        "verdict": _verdict(effects, naming_found.confounded, unexplained, confirmed=held["confirmed"]),
        "contact_law": law,
        "naming_base": naming_law.label,
        "effects": effects,
        "confounded": naming_found.confounded,
        "given_the_others": naming_found.given_the_others,
        "unexplained": unexplained,
        "open_world": open_world_record,
        "predictable": predictor,
        "velocities": steps.velocities,
        "free_flight": falling,
        "contact_signatures": steps.contact,
        "base_parameters": base.reported(base_values)["base"],
        "final_base_parameters": final.reported(final_values)["base"],
        "located": located,
        "located_after": locate.locate(steps, final, final_values) if final.effects else located,
        "heldout": held,
        "candidates": candidates,
        "decision_rule": {
            "margin": decision.margin,
            "later_margin": decision.later_margin,
            "confidence": decision.confidence,
            "rule": "val improvement over the model of its round > 0 at 95% (paired bootstrap over trajectories; for "
            "an effect free flight measures, on the val segments in free flight instead, the whole val not worse), "
            "closing >= margin of the base simulator's val loss in the first round and >= later_margin of its "
            "round's model's val loss after it or a significant gain on the val segments in free flight that removes "
            ">= later_margin of it (or, for gravity_scale, an apparent gravity, for air_drag and wind, a drag, "
            "measured model-free in free flight on val; never where free flight rules it out), and delta BIC < 0 on "
            "train; then the same against the model of its round refitted "
            "from the candidate's own values, where that refit gains on train (the refit control). Confirmed on the "
            "held-out test tosses: the full rollouts' position error improves (95% interval above zero); otherwise "
            "the name is an unconfirmed candidate, and the verdict `unexplained` where what the base misses is still "
            "predictable (the open-world correction passes, or a flexible predictor beats the base on test by more "
            "than it does on null data)",
        },
        "budget": budget.__dict__,
        "robust_scale": steps.train_fit.scale,
        "evaluations": steps.train_fit.evaluations + steps.val_fit.evaluations,
        "seconds": {
            **{k: round(v, 1) for k, v in steps.timings.items()},
            "total_s": round(time.perf_counter() - started, 1),
        },
    }
    arrays = {
        "before": before,
        "after": after,
        "final": final,
        "final_values": final_values,
        "base": base,
        "base_values": base_values,
        "steps": steps,
    }
    steps.close()  # the report may simulate again: the engines' workers start anew if it does
    return document, arrays
