"""What every step of the diagnosis shares: the dataset's splits, their short-horizon segments and fits, the budget,
the decision rule, the random stream and the model-free measurements; below the steps, which are functions of it
(diagnosis.pipeline runs them)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from contactbench.diagnosis import contact_signatures, free_flight, velocities
from contactbench.diagnosis.decision import Decision
from contactbench.diagnosis.fitting import ResidualFit
from contactbench.diagnosis.library import Hypothesis, library
from contactbench.diagnosis.segments import SegmentSimulator, cut_segments
from contactbench.errors import ContactbenchError
from contactbench.scene import Recordings, Split

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
    # The other engines' contact laws (diagnosis.contact_law): train trajectories their fits see (the first of the
    # diagnosis' own; naming on one of them fits on the same), and global-search evaluations per engine and option.
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
        self.engine_name = "mujoco"  # the base's engine: every fit below simulates in it (use_engine)
        self.timings: dict[str, float] = {}  # the pipeline's record of how long each step took
        self._test: tuple[Split, ResidualFit] | None = None  # test segments, cut when first needed
        self._halves: ResidualFit | None = None  # half-length val segments, cut when first needed

    def fit_base(
        self, hypothesis: Hypothesis | None = None, start: np.ndarray | None = None
    ) -> tuple[Hypothesis, np.ndarray]:
        """The base fitted on train (by default the diagnosis' own MuJoCo base, from a global search; from `start`,
        least squares only), and the robust loss every later fit and comparison uses calibrated on it."""
        started = time.perf_counter()
        hypothesis = Hypothesis(self.dataset.n_bodies) if hypothesis is None else hypothesis
        if start is None:
            start = self.train_fit.global_search(hypothesis, self.budget.base_evaluations, self.budget.batch, self.seed)
        self.val_fit.scale = self.train_fit.calibrate(hypothesis, start)
        values, loss = self.train_fit.least_squares(hypothesis, start, self.budget.lsq_iterations)
        log.info("base fit (%s): train loss %.5f, %s", hypothesis.engine, loss, hypothesis.reported(values)["base"])
        self.timings["base_fit_s"] = self.timings.get("base_fit_s", 0.0) + time.perf_counter() - started
        return hypothesis, values

    def use_engine(self, engine_name: str, effects: frozenset[str]) -> None:
        """Every later fit on this engine, with the library cut to the effects it models: on the same val segments,
        and on the train segments of the first law_trajectories train tosses, which its contact law was fitted on
        (an engine other than MuJoCo is stepped from Python, each evaluation many times MuJoCo's)."""
        self.close()
        self.engine_name = engine_name
        if engine_name != "mujoco":
            kept = min(self.budget.law_trajectories, self.train_split.n_trajectories)
            self.train_split = self.train_split.select(np.arange(kept))
            segments = self.train_fit.simulator.segments.of_trajectories(kept)
        else:
            segments = self.train_fit.simulator.segments
        self.train_fit, self.val_fit = (
            ResidualFit(SegmentSimulator(self.dataset, fit_segments, engine_name=engine_name), fit.scale)
            for fit, fit_segments in ((self.train_fit, segments), (self.val_fit, self.val_fit.simulator.segments))
        )
        self._test = self._halves = None
        self.library = {name: effect for name, effect in self.library.items() if name in effects}

    def close(self) -> None:
        """Release the engines' worker processes."""
        for fit in (self.train_fit, self.val_fit, self._halves, self._test[1] if self._test else None):
            if fit is not None:
                fit.simulator.close()

    def val_losses(self, hypothesis: Hypothesis, values: np.ndarray) -> np.ndarray:
        """Per-trajectory mean robust loss of the short-horizon residuals on val [N_val]."""
        residuals = self.val_fit.residuals(hypothesis, values[None])[0]
        return self.val_fit.simulator.trajectory_losses(self.val_fit.robust(residuals), self.val_split.n_trajectories)

    def test_segments(self) -> tuple[Split, ResidualFit]:
        """The test split and its short-horizon segments, cut once, scored with the robust loss of train."""
        if self._test is None:
            split = self.dataset.split("test")
            segments = cut_segments(self.dataset, split, self.budget.segment_frames)
            simulator = SegmentSimulator(self.dataset, segments, engine_name=self.engine_name)
            self._test = split, ResidualFit(simulator, scale=self.train_fit.scale)
        return self._test

    def half_segments(self) -> ResidualFit:
        """Half-length val segments (free-flight evidence, naming.airborne_gain), cut when first needed: few tosses fly
        clear of the floor for a whole segment, and many more for half of one."""
        if self._halves is None:
            segments = cut_segments(self.dataset, self.val_split, max(self.budget.segment_frames // 2, 1))
            simulator = SegmentSimulator(self.dataset, segments, engine_name=self.engine_name)
            self._halves = ResidualFit(simulator, scale=self.val_fit.scale)
        return self._halves
