"""MuJoCo's own system-identification toolbox, `mujoco.sysid` (the `mujoco[sysid]` extra), on sysid's problem
(model=mujoco_sysid): the same Table 2c parameters (search_space.SearchSpace), the same train tosses and eq. (1), the
same selection on val; what changes is the optimiser, and the fit reports each parameter's uncertainty.

What is the toolbox's: the parameters as `sysid.Parameter`s in a `sysid.ParameterDict` (physical units, box bounds,
`move_off_bounds` before a start), the optimisation by `sysid.optimize` (its default backend, MuJoCo's bounded
Levenberg-Marquardt `mujoco.minimize.least_squares`, finite-difference Jacobians), the Jacobian at the optimum by
`mujoco.minimize.jacobian_fd`, and the covariance and confidence intervals by `sysid.calculate_intervals`.

What is ours: the residuals. The toolbox's own residual (`sysid.residual`) compares sensor signals, each normalised by
its own norm over the toss, from one native rollout per toss; here the residual is eq. (1) itself (EquationOneResiduals:
its sum of squares is the loss `sysid` minimises), rolled out by the engine that scores every MuJoCo model, so the two
fits differ by their optimiser alone. One trainer step runs one restart's whole least-squares fit; the restarts after
the first start from random frictions and stiffness, and the best on val is kept, as for `sysid`.

The intervals are the toolbox's: Gauss-Newton (Laplace) intervals that treat every residual as independent noise. The
frames of one toss are not independent, so they are narrower than the spread over refits on other tosses would be; a
parameter the data cannot move (the smaller of an object's and the floor's friction: MuJoCo takes the larger) has
none (null).
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import time

import numpy as np
import pytorch_lightning as pl
import torch

from contactbench.errors import ContactbenchError, require_positive_integers
from contactbench.models.sysid import uncertainty
from contactbench.models.sysid.module import IdentifiedModule, fixed_subset, package_versions, save_last_checkpoint
from contactbench.models.sysid.uncertainty import EquationOneResiduals, intervals, summary, toolbox
from contactbench.recordings import Recordings
from contactbench.sim import mujoco_engine
from contactbench.sim.engines import Dimension

log = logging.getLogger(__name__)

BACKENDS = ("mujoco", "scipy", "scipy_parallel_fd")  # sysid.optimize's least-squares backends


def dimensions(n_bodies: int, n_joints: int) -> tuple[Dimension, ...]:
    """SearchSpace's dimensions in its order, with their ranges, scales and starts."""
    return uncertainty.dimensions("mujoco", n_bodies, n_joints)


def start_vector(module: ToolboxSysIDModule, restart: int) -> np.ndarray:
    """Restart 0 starts where NGOpt's search does (the domain's centre, damping 50, hinges at their start), later
    restarts from objects' frictions and a stiffness (log-uniform) drawn at random; damping and the hinges keep their
    starts, which they have because much of their range diverges at the datasets' frame time. The floor's friction
    starts at its lower bound in every restart: MuJoCo takes the larger of an object's and the floor's friction, and
    where the two are near each other (both 0.5 at NGOpt's start) the finite-difference steps straddle the kink of
    that max, which slows the least-squares steps or, at small steps, stops them; below every object's, each object's
    own friction acts."""
    h = module.hparams
    space = module.space
    start = space.to_vector(space.to_parameters(space.parametrization(seed=h.seed).value))
    if restart > 0:
        rng = np.random.default_rng([h.seed, restart])
        for k, d in enumerate(dimensions(space.n_bodies, space.n_joints)):
            if d.init is None:
                start[k] = np.exp(rng.uniform(np.log(d.low), np.log(d.high))) if d.log else rng.uniform(d.low, d.high)
    start[space.names.index("floor_friction")] = mujoco_engine.FRICTION[0]  # moved off the bound before the fit
    return start


class ToolboxSysIDModule(IdentifiedModule):
    """sysid's parameters identified by mujoco.sysid; holds the settings, what val selected and its uncertainty."""

    model_name = "mujoco_sysid"

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int,
        restarts: int,
        max_iters: int,
        train_trajectories: int | None,
        val_trajectories: int | None,
        optimizer: str = "mujoco",
        diff_step: float = 0.03,
        confidence: float = 0.95,
        seed: int = 0,
        position_exponent: int = 2,
        unstable_penalty: float = 1e3,
        timeout_s: float = 120.0,
        nthread: int | None = None,
        substeps: int = 1,
        engine: str = "mujoco",
    ):
        if engine != "mujoco":
            raise ContactbenchError(f"model.module.engine is {engine!r} (expected mujoco: mujoco.sysid is MuJoCo's)")
        if optimizer not in BACKENDS:
            raise ContactbenchError(f"model.module.optimizer is {optimizer!r} (expected one of {', '.join(BACKENDS)})")
        if not (0 < confidence < 1 and diff_step > 0):
            raise ContactbenchError(
                f"model.module.confidence is {confidence} and diff_step {diff_step} (expected 0 < confidence < 1, "
                "diff_step > 0)"
            )
        require_positive_integers(
            {
                "restarts": restarts,
                "max_iters": max_iters,
                "train_trajectories": train_trajectories,
                "val_trajectories": val_trajectories,
            },
            optional=("train_trajectories", "val_trajectories"),
        )
        toolbox()
        super().__init__(dataset, engine)
        self.save_hyperparameters(ignore=["dataset"], logger=False)
        n = len(self.space.names)
        self.register_buffer("selected_interval", torch.full((n,), float("nan"), dtype=torch.float64))
        self.register_buffer("selected_covariance", torch.full((n, n), float("nan"), dtype=torch.float64))
        self.register_buffer("selected_record", torch.full((4,), float("nan"), dtype=torch.float64))

    def select_fit(self, result: dict) -> None:
        """The restart val chose: its parameters, their half-width intervals (inf: not identifiable), covariance and
        [train loss, iterations, evaluations, seconds]."""
        self.select(result["vector"], result["val_loss"])
        self.selected_interval.copy_(torch.tensor(result["interval"], dtype=torch.float64))
        self.selected_covariance.copy_(torch.tensor(result["covariance"], dtype=torch.float64))
        record = [result["train_loss"], result["iterations"], result["evaluations"], result["seconds"]]
        self.selected_record.copy_(torch.tensor(record, dtype=torch.float64))

    def fitted_summary(self) -> dict:
        h = self.hparams
        train_loss, iterations, evaluations, seconds = self.selected_record.tolist()
        return {
            **super().fitted_summary(),
            "train_loss": train_loss,
            **summary(
                self.space.names,
                self.selected.cpu().numpy(),
                self.selected_interval.cpu().numpy(),
                self.selected_covariance.cpu().numpy(),
                dimensions(self.space.n_bodies, self.space.n_joints),
                h.confidence,
            ),
            "optimizer": {
                "name": "mujoco.sysid.optimize",
                "backend": h.optimizer,
                "iterations": int(iterations),
                "evaluations": int(evaluations),
                "seconds": seconds,
            },
            "versions": package_versions("mujoco", "scipy"),
        }


class LeastSquaresSearch(pl.Callback):
    """One training step per restart: mujoco.sysid's least-squares fit from that restart's start on the train tosses,
    its intervals at the optimum, the val score; the restart with the best val score is selected. The checkpoint
    holds each finished restart's numbers: a resumed run goes on at the next restart."""

    def __init__(self):
        self.results: list[dict] = []

    def on_fit_start(self, trainer, module: ToolboxSysIDModule) -> None:
        h = module.hparams
        self.rollouts = module.rollouts()
        n_train = len(module.dataset.split("train").poses)
        indices = fixed_subset(n_train, h.train_trajectories, h.seed + 1)  # a fixed subset: least squares needs one
        self.train = EquationOneResiduals(
            module.dataset,
            "train",
            h.context_frames,
            self.rollouts,
            position_exponent=h.position_exponent,
            unstable_penalty=h.unstable_penalty,
            indices=indices,
        )
        self.val_objective = module.objective("val", self.rollouts)
        log.info(
            "mujoco_sysid: %d train tosses, restart %d/%d",
            self.train.n_trajectories,
            min(len(self.results) + 1, h.restarts),
            h.restarts,
        )

    def on_fit_end(self, trainer, module) -> None:
        self.val_objective.close()
        self.rollouts.close()

    def on_train_batch_start(self, trainer, module: ToolboxSysIDModule, batch, batch_index) -> None:
        h = module.hparams
        if len(self.results) >= h.restarts:  # a resumed run that had already finished
            trainer.should_stop = True
            return
        restart = len(self.results)
        result = fit(module, self.train, start_vector(module, restart))
        parameters = module.space.from_vector(result["vector"])
        val_indices = fixed_subset(self.val_objective.n_trajectories, h.val_trajectories, h.seed)
        result["val_loss"] = float(self.val_objective([parameters], val_indices).losses[0])
        self.results.append(result)
        module.log_dict(
            {
                "train/loss": result["train_loss"],
                "train/evaluations": float(sum(r["evaluations"] for r in self.results)),
                "train/restart": float(restart),
                "val/loss": result["val_loss"],
                **{f"params/{k}": v for k, v in module.space.describe(parameters).items()},
            },
            on_step=True,
        )
        log.info(
            "mujoco_sysid restart %d/%d: %d iterations, train loss %.5f, val loss %.5f with %s",
            restart + 1,
            h.restarts,
            result["iterations"],
            result["train_loss"],
            result["val_loss"],
            module.space.describe(parameters),
        )
        module.select_fit(min(self.results, key=lambda r: r["val_loss"]))
        trainer.should_stop = len(self.results) >= h.restarts
        save_last_checkpoint(trainer)

    # ------------------------------------------------------------ checkpointing

    @staticmethod
    def check_state(state: object, where: str) -> None:
        """Checked before a resume loads anything (contactbench.folders.check_checkpoint)."""
        check_fit_state(state, where)

    def state_dict(self) -> dict:
        return {"results": self.results}

    def load_state_dict(self, state: dict) -> None:
        check_fit_state(state, "checkpoint least-squares state")
        self.results = [dict(r) for r in state["results"]]


def fit(module: ToolboxSysIDModule, train: EquationOneResiduals, start: np.ndarray) -> dict:
    """One least-squares fit by mujoco.sysid from `start`, with the intervals at its optimum."""
    sysid = toolbox()
    h = module.hparams
    names = module.space.names
    params = sysid.ParameterDict()
    for name, value, d in zip(names, start, dimensions(module.space.n_bodies, module.space.n_joints)):
        params.add(sysid.Parameter(name, nominal=value, min_value=d.low, max_value=d.high))
    params.move_off_bounds()  # the toolbox's advice: a start on a bound can stall its solver there
    evaluations = 0

    evaluated = uncertainty.residual_function(train, module.space)

    def residuals(x: np.ndarray) -> np.ndarray:
        nonlocal evaluations
        evaluations += 1 if np.ndim(x) == 1 else np.shape(x)[1]
        return evaluated(x)

    def residual_fn(x, _params):  # the signature sysid.optimize calls, as sysid.build_residual_fn's closures have it
        return [residuals(x)], [], []

    started = time.perf_counter()
    kwargs = {"max_iters": h.max_iters, ("eps" if h.optimizer == "mujoco" else "diff_step"): h.diff_step}
    # sysid.optimize gives its backend no verbosity (its own `verbose` takes the keyword): the backend prints every
    # iteration to stdout, which goes to a buffer and, in short, to the log
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        found, result = sysid.optimize(params, residual_fn, optimizer=h.optimizer, verbose=False, **kwargs)
    x = np.clip(found.as_vector(), *found.get_bounds())
    at_optimum = residuals(x)
    space = dimensions(module.space.n_bodies, module.space.n_joints)
    interval, covariance = intervals(residuals, x, space, h.confidence, h.diff_step, at_optimum)
    ended = [line for line in printed.getvalue().splitlines() if line.startswith(("Terminated", "`"))]
    log.info("mujoco.sysid (%s): %s", h.optimizer, ended[0].strip() if ended else "done")
    return {
        "vector": module.space.to_vector(module.space.from_vector(x)).tolist(),
        "train_loss": float(np.dot(at_optimum, at_optimum)),
        "interval": [float(v) for v in interval],
        "covariance": np.asarray(covariance, float).tolist(),
        "iterations": iterations(result, ended[0] if ended else ""),
        "evaluations": evaluations,
        "seconds": time.perf_counter() - started,
    }


def iterations(result, ended: str) -> int:
    """Iterations of a fit, as MuJoCo's backend reports them when it ends; scipy's backend counts its Jacobians."""
    said = re.search(r"after (\d+) iterations", ended)
    return int(said.group(1)) if said else int(result.get("njev") or result.get("nfev") or 0)


FIELDS = ("vector", "val_loss", "train_loss", "interval", "covariance", "iterations", "evaluations", "seconds")


def check_fit_state(state: object, where: str) -> None:
    """Refuse anything but the numbers-only state LeastSquaresSearch.state_dict writes, in one line."""
    if not isinstance(state, dict) or set(state) != {"results"} or not isinstance(state["results"], list):
        raise ContactbenchError(f"{where}: expected {{'results': [one dict per finished restart]}}, got {state!r:.80}")
    for k, result in enumerate(state["results"]):
        if not isinstance(result, dict) or set(result) != set(FIELDS):
            raise ContactbenchError(f"{where}: results[{k}] is malformed (expected the fields {', '.join(FIELDS)})")
        n = len(result["vector"]) if isinstance(result["vector"], list) else -1
        numbers = [result[f] for f in ("val_loss", "train_loss", "iterations", "evaluations", "seconds")]
        flat = [*result["vector"], *result["interval"]] if n >= 0 and isinstance(result["interval"], list) else None
        rows = result["covariance"]
        if (
            flat is None
            or len(result["interval"]) != n
            or not isinstance(rows, list)
            or len(rows) != n
            or not all(isinstance(row, list) and len(row) == n for row in rows)
            or not all(_is_number(x) for x in [*numbers, *flat, *(x for row in rows for x in row)])
        ):
            raise ContactbenchError(
                f"{where}: results[{k}] holds other than numbers of matching sizes (vector, interval and covariance)"
            )


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)
