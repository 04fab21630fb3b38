"""Fit a hypothesis (base simulator + effects) to short-horizon residuals: global search, then least squares."""

from __future__ import annotations

import logging

import nevergrad as ng
import numpy as np
import scipy.optimize

from contactbench.diagnosis.library import Hypothesis
from contactbench.diagnosis.segments import UNSTABLE_RESIDUAL, SegmentSimulator

log = logging.getLogger(__name__)
# Forward-difference step in the unit box of every parameter: contact makes the residuals piecewise smooth, so the
# step must be wide enough to see the trend, not a kink.
DIFFERENCE_STEP = 0.01
LINE_SEARCH = (1.0, 0.5, 0.25, 0.1, 0.03)


class ResidualFit:
    """Residual vectors of hypotheses on one set of segments; fits work in each parameter's unit box [0, 1]."""

    def __init__(self, simulator: SegmentSimulator, scale: float | None = None):
        self.simulator = simulator
        self.evaluations = 0
        # Residuals beyond `scale` count less and less (soft L1): the engines' different impacts leave a few large
        # residuals that would otherwise outweigh a small, steady drift everywhere else. None: plain squares.
        self.scale = scale

    def residuals(self, hypothesis: Hypothesis, internal: np.ndarray) -> np.ndarray:
        """[B, M, L, K, 6] for internal parameter vectors [B, P]; sets the engine rejects score as unstable."""
        internal = np.atleast_2d(internal)
        params, valid = [], []
        for values in internal:
            try:
                candidate = hypothesis.contact_parameters(values)
                self.simulator.rollouts.check(candidate)  # MuJoCo may refuse to compile, e.g. an impossible inertia
                params.append(candidate)
                valid.append(True)
            except Exception as error:  # noqa: BLE001 - any refusal is a bad candidate, not a crash
                log.debug("candidate rejected: %s", error)
                valid.append(False)
        out = np.full((len(internal), *self.simulator.segments.truth.shape[:3], 6), UNSTABLE_RESIDUAL)
        if params:
            out[np.array(valid)] = self.simulator.residuals(params)
        self.evaluations += len(internal)
        return out

    @property
    def entries(self) -> int:
        """Residual 6-vectors per parameter set: segments x frames x bodies."""
        return int(np.prod(self.simulator.segments.truth.shape[:3]))

    def vector(self, hypothesis: Hypothesis, internal: np.ndarray) -> np.ndarray:
        """Flat residual vectors [B, R] whose squared norm is the mean squared residual."""
        residuals = self.residuals(hypothesis, internal)
        return residuals.reshape(len(residuals), -1) / np.sqrt(self.entries)

    def loss(self, hypothesis: Hypothesis, internal: np.ndarray) -> np.ndarray:
        """Mean robust loss per parameter vector [B]."""
        residuals = self.residuals(hypothesis, internal)
        return self.robust(residuals).reshape(len(residuals), -1).sum(axis=-1) / self.entries

    def _jacobian(self, hypothesis: Hypothesis, unit: np.ndarray, at_unit: np.ndarray) -> np.ndarray:
        """Forward differences [R, P] around `unit` (whose residual vector is `at_unit`), all steps in one batched
        call; a step that would leave the unit box goes the other way."""
        lower, upper = hypothesis.bounds()
        steps = np.where(unit + DIFFERENCE_STEP <= 1.0, DIFFERENCE_STEP, -DIFFERENCE_STEP)
        shifted = unit[None, :] + np.diag(steps)
        return ((self.vector(hypothesis, lower + shifted * (upper - lower)) - at_unit[None, :]) / steps[:, None]).T

    def robust(self, residuals: np.ndarray) -> np.ndarray:
        """Per-entry loss: r^2, or soft L1 2 f^2 (sqrt(1 + (r/f)^2) - 1), which is r^2 for small r."""
        if self.scale is None:
            return residuals**2
        return 2 * self.scale**2 * (np.sqrt(1 + (residuals / self.scale) ** 2) - 1)

    def calibrate(self, hypothesis: Hypothesis, internal: np.ndarray) -> float:
        """Set the robust scale to twice the median absolute residual of a fitted hypothesis."""
        residuals = self.residuals(hypothesis, internal[None])[0]
        self.scale = max(2.0 * float(np.median(np.abs(residuals))), 1e-6)
        return self.scale

    # ---------------------------------------------------------------- searches

    def global_search(self, hypothesis: Hypothesis, budget: int, batch: int, seed: int) -> np.ndarray:
        """NGOpt over the unit box from the hypothesis' start, `batch` candidates per batched rollout."""
        lower, upper = hypothesis.bounds()
        start = (hypothesis.start() - lower) / (upper - lower)
        parametrization = ng.p.Array(init=start, lower=0.0, upper=1.0)
        parametrization.random_state = np.random.RandomState(seed)
        optimizer = ng.optimizers.NGOpt(parametrization=parametrization, budget=budget, num_workers=batch)
        for _ in range(max(1, budget // batch)):
            asked = [optimizer.ask() for _ in range(batch)]
            losses = self.loss(hypothesis, lower + np.stack([a.value for a in asked]) * (upper - lower))
            for candidate, value in zip(asked, losses):
                optimizer.tell(candidate, float(value))
        return lower + np.clip(optimizer.provide_recommendation().value, 0.0, 1.0) * (upper - lower)

    def least_squares(self, hypothesis: Hypothesis, start: np.ndarray, iterations: int) -> tuple[np.ndarray, float]:
        """Trust-region least squares from `start` (internal), batched forward-difference Jacobians."""
        lower, upper = hypothesis.bounds()
        span = upper - lower
        cache: dict[bytes, np.ndarray] = {}

        def value(unit: np.ndarray) -> np.ndarray:
            key = unit.tobytes()
            if key not in cache:
                cache.clear()
                cache[key] = self.vector(hypothesis, lower + unit * span)[0]
            return cache[key]

        unit0 = np.clip((start - lower) / span, 0.0, 1.0)
        loss_kind = ("linear", 1.0) if self.scale is None else ("soft_l1", self.scale / np.sqrt(self.entries))
        result = scipy.optimize.least_squares(
            value,
            unit0,
            jac=lambda unit: self._jacobian(hypothesis, unit, value(unit)),
            bounds=(0.0, 1.0),
            method="trf",
            max_nfev=iterations,
            x_scale=1.0,
            loss=loss_kind[0],
            f_scale=loss_kind[1],
        )
        losses = self.loss(hypothesis, lower + np.stack([unit0, result.x]) * span)
        unit = result.x if losses[1] <= losses[0] else unit0
        return lower + unit * span, float(min(losses))

    def fit_effect(
        self, hypothesis: Hypothesis, start: np.ndarray, free: int, iterations: int
    ) -> tuple[np.ndarray, float]:
        """Least squares from `start` and from the best point of a quartile grid over the last `free` parameters (the
        effect's); the better fit wins. Least squares is local: an effect's optimum may lie far from "off" (a raised
        floor), but a coarse grid can also land beside a valley that the plain start descends into (a tilted floor)."""
        fits = [self.least_squares(hypothesis, start, iterations)]
        grid_start = self.best_start(hypothesis, start, free)
        if not np.array_equal(grid_start, start):
            fits.append(self.least_squares(hypothesis, grid_start, iterations))
        return min(fits, key=lambda fit: fit[1])

    def best_start(self, hypothesis: Hypothesis, start: np.ndarray, free: int) -> np.ndarray:
        """`start`, or a point with one of the last `free` parameters moved to a quartile of its range, whichever
        has the least loss (one batched call)."""
        lower, upper = hypothesis.bounds()
        points = [start]
        for index in range(len(start) - free, len(start)):
            for quartile in (0.25, 0.75):
                moved = start.copy()
                moved[index] = lower[index] + quartile * (upper[index] - lower[index])
                points.append(moved)
        points = np.stack(points)
        return points[int(np.argmin(self.loss(hypothesis, points)))]

    def screen(self, hypothesis: Hypothesis, start: np.ndarray) -> float:
        """The loss after one bounded Gauss-Newton step from `start`, shortened by a line search (all step lengths in
        one batched call): a cheap screen of how much an effect can explain."""
        lower, upper = hypothesis.bounds()
        span = upper - lower
        unit = np.clip((start - lower) / span, 0.0, 1.0)
        at_unit = self.vector(hypothesis, (lower + unit * span)[None])[0]
        step = scipy.optimize.lsq_linear(
            self._jacobian(hypothesis, unit, at_unit), -at_unit, bounds=(-unit, 1.0 - unit)
        ).x
        # The linear model only proposes the direction; the score is the best loss actually reached along it.
        trials = unit[None, :] + np.array(LINE_SEARCH)[:, None] * step[None, :]
        reached = self.loss(hypothesis, lower + np.vstack([unit, trials]) * span)
        return float(reached.min())
