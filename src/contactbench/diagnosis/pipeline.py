"""The diagnosis of a dataset as its four steps: fit the base simulator, then locate, name, model and prove.

Diagnosis holds what every step shares (the splits, their short-horizon segments and fits, the random stream); each
step is a module of functions of it: locate.py, naming.py (name), open_world.py and predictable.py (model what the
library does not name), proof.py (prove on the held-out test split)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from contactbench.diagnosis import (
    contact_law,
    contact_signatures,
    free_flight,
    locate,
    naming,
    open_world,
    predictable,
    proof,
    simulated_drag,
    velocities,
)
from contactbench.diagnosis.decision import Decision
from contactbench.diagnosis.fitting import ResidualFit
from contactbench.diagnosis.free_flight import MEASURED
from contactbench.diagnosis.library import Hypothesis, library
from contactbench.diagnosis.segments import SegmentSimulator, cut_segments
from contactbench.errors import ContactbenchError
from contactbench.recordings import Recordings, Split

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Budget:
    segment_frames: int = 16  # frames simulated from each recorded state before the next reset
    fit_trajectories: int = 60  # train trajectories the fits see
    val_trajectories: int = 120  # val trajectories that judge the candidates
    base_evaluations: int = 160  # NGOpt evaluations of the base parameters before least squares
    batch: int = 16  # candidates per batched rollout in the global search
    lsq_iterations: int = 12  # least-squares function evaluations per fit (each Jacobian adds one batch)
    front_runners: int = 10  # effects fitted in full after screening, per round (10: the whole library)
    max_effects: int = 2
    bootstrap: int = 1000
    open_world_terms: int = 8  # most terms of the open-world correction (diagnosis.open_world)
    # The other engines' contact laws (diagnosis.contact_law): train trajectories their fits see, and global-search
    # evaluations per engine and contact option.
    law_trajectories: int = 60
    law_evaluations: int = 160


def _pick(rng: np.random.Generator, count: int, limit: int) -> np.ndarray:
    return np.sort(rng.choice(count, size=min(count, limit), replace=False))


class Diagnosis:
    """What the steps share, on a dataset the models may see (train, val, test; no meta.generator)."""

    def __init__(
        self,
        dataset: Recordings,
        budget: Budget = Budget(),
        decision: Decision = Decision(),
        *,
        seed: int = 0,
        context_frames: int = 6,
    ):
        if "generator" in dataset.meta:
            raise ContactbenchError("diagnosis must not see meta.generator: pass dataset.for_models([...])")
        # Recorded velocities in the convention the simulators restart from (diagnosis.velocities; its own generator,
        # as the model-free checks below: the steps' draws stay as they were).
        self.velocities = velocities.check(dataset, np.random.default_rng(seed), budget.bootstrap, decision.confidence)
        dataset = velocities.aligned(dataset, self.velocities)
        self.dataset = dataset
        self.budget = budget
        self.decision = decision
        self.context_frames = context_frames
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        # First, model-free: do bodies in free flight fall at meta.gravity, and does a drag slow them? (Its own
        # generator: the steps' draws stay as they were.) Its train measurement is where the gravity_scale effect's
        # fit starts.
        self.free_flight = free_flight.check(
            dataset, np.random.default_rng(seed), budget.bootstrap, decision.confidence
        )
        # And in contact: friction against slip direction, speed and place, spin and roll decay, bounces.
        self.contact = contact_signatures.measure(
            dataset, np.random.default_rng(seed), budget.bootstrap, decision.confidence
        )
        self.library = library(
            float(dataset.widths().max()),
            self.free_flight["scale"] or 1.0,
            self.free_flight["gravity_evidence"],
            self.free_flight["drag_evidence"],
            self.contact["evidence"],
        )
        train, val = dataset.split("train"), dataset.split("val")
        fit_rows = _pick(self.rng, train.n_trajectories, budget.fit_trajectories)
        val_rows = _pick(self.rng, val.n_trajectories, budget.val_trajectories)
        self.train_split = train.select(fit_rows)
        self.train_fit = ResidualFit(
            SegmentSimulator(dataset, cut_segments(dataset, self.train_split, budget.segment_frames))
        )
        self.val_split = val.select(val_rows)
        self.val_fit = ResidualFit(
            SegmentSimulator(dataset, cut_segments(dataset, self.val_split, budget.segment_frames))
        )
        self.timings: dict[str, float] = {}
        self.confounded: list[str] = []  # effects the first naming round could not tell apart
        self.given_the_others: list[dict] = []  # each named effect judged against the model without it
        self._test: tuple[Split, ResidualFit] | None = None  # test segments, cut when first needed
        self._halves: ResidualFit | None = None  # half-length val segments, cut when first needed

    def fit_base(self) -> tuple[Hypothesis, np.ndarray]:
        started = time.perf_counter()
        hypothesis = Hypothesis(self.dataset.n_bodies)
        values = self.train_fit.global_search(hypothesis, self.budget.base_evaluations, self.budget.batch, self.seed)
        # From here on every fit and comparison uses the same robust loss.
        self.val_fit.scale = self.train_fit.calibrate(hypothesis, values)
        values, loss = self.train_fit.least_squares(hypothesis, values, self.budget.lsq_iterations)
        log.info("base fit: train loss %.5f, %s", loss, hypothesis.reported(values)["base"])
        self.timings["base_fit_s"] = time.perf_counter() - started
        return hypothesis, values

    def val_losses(self, hypothesis: Hypothesis, values: np.ndarray) -> np.ndarray:
        """Per-trajectory mean robust loss of the short-horizon residuals on val [N_val]."""
        residuals = self.val_fit.residuals(hypothesis, values[None])[0]
        return self.val_fit.simulator.trajectory_losses(self.val_fit.robust(residuals), self.val_split.n_trajectories)

    def test_segments(self) -> tuple[Split, ResidualFit]:
        """The test split and its short-horizon segments, cut once, scored with the robust loss of train."""
        if self._test is None:
            split = self.dataset.split("test")
            segments = SegmentSimulator(self.dataset, cut_segments(self.dataset, split, self.budget.segment_frames))
            self._test = split, ResidualFit(segments, scale=self.train_fit.scale)
        return self._test

    def half_segments(self) -> ResidualFit:
        """Half-length val segments (free-flight evidence, naming.airborne_gain), cut when first needed: few tosses fly
        clear of the floor for a whole 16-frame segment (a tetrahedron's: 15 of 165 val tosses; at 8 frames 163)."""
        if self._halves is None:
            segments = cut_segments(self.dataset, self.val_split, max(self.budget.segment_frames // 2, 1))
            self._halves = ResidualFit(SegmentSimulator(self.dataset, segments), scale=self.val_fit.scale)
        return self._halves


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
    pass: a brick's floor friction 1.3x larger along x than y, measured and confirmed on test, closed 1.1% of the
    base val loss as MuJoCo's anisotropy)."""
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


def run_diagnosis(
    dataset: Recordings,
    budget: Budget = Budget(),
    decision: Decision = Decision(),
    *,
    seed: int = 0,
    context_frames: int = 6,
    engines: tuple[str, ...] = contact_law.ENGINES,
) -> tuple[dict, dict]:
    """The diagnosis document (diagnosis.json) and the arrays its report draws; `engines`: the contact laws compared
    (diagnosis.contact_law), MuJoCo among them."""
    started = time.perf_counter()
    contact_law.check_engines(engines)
    steps = Diagnosis(dataset, budget, decision, seed=seed, context_frames=context_frames)
    falling = steps.free_flight
    log.info("%s", falling["sentence"])
    base, base_values = steps.fit_base()
    # The contact law first: every engine fitted alike, the best on val, what the others miss where, on test.
    law, _ = contact_law.compare(steps, base, base_values, engines)
    log.info("contact law: %s", law["finding"])
    located = locate.locate(steps, base, base_values)
    final, final_values, candidates = naming.name_effects(steps, base, base_values)
    named_on_val = final.names
    final, final_values, each_on_test = proof.each_effect(steps, final, final_values)
    held, before, after = proof.prove(steps, base, base_values, final, final_values)
    held["each_effect"] = each_on_test
    open_world_record = predictor = unexplained = None
    if not held["confirmed"] and not steps.confounded:
        # Nothing named is proven: before saying `none` (or leaving an unconfirmed name as the answer), is what the
        # model misses predictable? First the sparse correction (terms a person can read), then a flexible predictor;
        # both of the model named on val (the base where nothing was), so that what an unconfirmed candidate does
        # explain is not read as something missing besides it.
        open_world_record = open_world.explain(steps, final, final_values)
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
        if effect.name == "air_drag" and "drag_ci95" in falling["splits"].get("val", {}):
            # wind is left out: free flight measures its drag in moving air, not the drag's size
            simulated = simulated_drag.drag_per_metre(dataset, final.contact_parameters(final_values), steps.rng)
            effects[-1]["against_free_flight"] = simulated_drag.against_free_flight(simulated, falling["splits"]["val"])
    document = {
        "verdict": _verdict(effects, steps.confounded, unexplained, confirmed=held["confirmed"]),
        "contact_law": law,
        # The library is modelled in MuJoCo only so far: names are fitted and proven on MuJoCo whichever law fits best.
        "naming_base": "mujoco",
        "effects": effects,
        "confounded": steps.confounded,
        "given_the_others": steps.given_the_others,
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
    return document, arrays
