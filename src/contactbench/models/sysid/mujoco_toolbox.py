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
from mujoco import minimize

from contactbench import rotations
from contactbench.errors import ContactbenchError, require_positive_integers
from contactbench.models.sysid.module import IdentifiedModule, package_versions, save_last_checkpoint, val_subset
from contactbench.models.sysid.objective import length_groups, subset
from contactbench.protocol import make_context
from contactbench.recordings import Recordings
from contactbench.sim import articulation, engines, mujoco_engine
from contactbench.sim.engines import Dimension
from contactbench.sim.rollout import Rollouts

log = logging.getLogger(__name__)

BACKENDS = ("mujoco", "scipy", "scipy_parallel_fd")  # sysid.optimize's least-squares backends
UNITS = {  # Table 2c and the articulation in physical units (MuJoCo's direct solref: aref = -k r - b v, per unit mass)
    "object_friction": "1",
    "floor_friction": "1",
    "floor_stiffness": "1/s^2",
    "floor_damping": "1/s",
    "joint_damping": "N m s/rad",
    "joint_friction": "N m",
    "inertia_scale": "1",
}


def toolbox():
    """mujoco.sysid, or one line saying how to install it (the package hides a missing extra's ImportError)."""
    from mujoco import sysid

    if not hasattr(sysid, "optimize"):
        raise ContactbenchError(
            "model=mujoco_sysid needs MuJoCo's sysid extra: pip install 'mujoco[sysid]==3.17.0' "
            "(make main and make test install it)"
        )
    return sysid


def unit(name: str) -> str:
    return UNITS[name.rstrip("0123456789").rstrip("_")]


class EquationOneResiduals:
    """Eq. (1) on a split's tosses as least-squares residuals: per scored frame and body, the position offset scaled by
    (2/w)^(p/2) and the rotation vector from the recorded to the predicted orientation (its norm is eq. (1)'s angle),
    each toss weighted by 1/sqrt(N x its scored frames). The sum of squares is then the ConfigurationObjective's loss:
    the mean over tosses of each toss's mean over its frames. An unstable candidate gets a flat residual whose sum of
    squares is `unstable_penalty`."""

    def __init__(
        self,
        dataset: Recordings,
        split: str,
        context_frames: int,
        rollouts: Rollouts,
        *,
        position_exponent: int = 2,
        unstable_penalty: float = 1e3,
        indices: np.ndarray | None = None,
    ):
        recorded = dataset.split(split)
        context = make_context(recorded, dataset.dt, context_frames)
        indices = np.arange(len(recorded.poses)) if indices is None else np.asarray(indices)
        self.context = subset(context, indices)
        self.truth = recorded.poses[indices]
        self.rollouts = rollouts
        self.unstable_penalty = float(unstable_penalty)
        self.steps = self.context.lengths - self.context.n_context  # scored frames per toss
        self.groups = length_groups(self.steps)
        self.position_weight = (2.0 / np.asarray(dataset.widths(), float)) ** (position_exponent / 2)  # [K]
        self.toss_weight = 1.0 / np.sqrt(len(indices) * self.steps)  # [N]
        self.size = int(self.steps.sum()) * dataset.n_bodies * 6

    @property
    def n_trajectories(self) -> int:
        return len(self.truth)

    def __call__(self, candidates: list) -> tuple[np.ndarray, np.ndarray]:
        """Residuals [B, size] and whether each candidate was unstable [B], for B parameter sets."""
        n = self.context.n_context
        parts, unstable = [], np.zeros(len(candidates), dtype=bool)
        for group in self.groups:
            horizon = int(self.steps[group].max())
            result = self.rollouts.simulate(
                candidates, self.context.poses[group, -1], self.context.velocities[group, -1], horizon
            )
            scored = np.arange(horizon)[None, :] < self.steps[group, None]  # [n, H]
            truth = self.truth[group, n : n + horizon]  # [n, H, K, 7]
            with np.errstate(invalid="ignore", over="ignore"):
                position = (truth[..., :3] - result.poses[..., :3]) * self.position_weight[:, None]
                relative = rotations.multiply(rotations.conjugate(truth[..., 3:]), result.poses[..., 3:])
                rotation = rotations.to_rotation_vector(relative)
                residual = np.concatenate([position, rotation], axis=-1) * self.toss_weight[group, None, None, None]
            parts.append(residual[:, scored].reshape(len(candidates), -1))  # [B, scored frames x K x 6]
            unstable |= (result.unstable_frames & scored).any(axis=(1, 2))
        residuals = np.concatenate(parts, axis=1)
        unstable |= ~np.isfinite(residuals).all(axis=1)
        residuals[unstable] = np.sqrt(self.unstable_penalty / self.size)
        return residuals, unstable


def dimensions(n_bodies: int, n_joints: int) -> tuple[Dimension, ...]:
    """SearchSpace's dimensions in its order, with their ranges, scales and starts."""
    return engines.engine("mujoco").dimensions(n_bodies) + articulation.dimensions(n_joints)


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
        names = self.space.names
        values = self.selected.cpu().numpy()
        interval = self.selected_interval.cpu().numpy()
        covariance = self.selected_covariance.cpu().numpy()
        bounds = [(d.low, d.high) for d in dimensions(self.space.n_bodies, self.space.n_joints)]
        identifiable = np.isfinite(interval)
        uncertainty = {}
        for k, name in enumerate(names):
            low, high = bounds[k]
            finite = bool(identifiable[k])
            uncertainty[name] = {
                "value": float(values[k]),
                "unit": unit(name),
                "std": float(np.sqrt(max(covariance[k, k], 0.0))) if finite else None,
                # the interval clipped to the searched range: the optimum may sit on a bound
                "interval": [float(max(values[k] - interval[k], low)), float(min(values[k] + interval[k], high))]
                if finite
                else None,
                "at_bound": bool(np.isclose(values[k], low) or np.isclose(values[k], high)),
            }
        # the toolbox's covariance keeps numbers where the data leave a direction free (a clamped zero eigenvalue):
        # null there, as the interval is
        matrix = [
            [float(covariance[i, j]) if identifiable[i] and identifiable[j] else None for j in range(len(names))]
            for i in range(len(names))
        ]
        train_loss, iterations, evaluations, seconds = self.selected_record.tolist()
        return {
            **super().fitted_summary(),
            "train_loss": train_loss,
            "uncertainty": {"confidence": h.confidence, "parameters": uncertainty},
            "covariance": {
                "names": names,
                "matrix": matrix,
            },
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
        indices = val_subset(n_train, h.train_trajectories, h.seed + 1)  # a fixed subset: least squares needs one
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
        val_indices = val_subset(self.val_objective.n_trajectories, h.val_trajectories, h.seed)
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

    def residuals(x: np.ndarray) -> np.ndarray:
        """[size] for one point, [size, k] for k points (the finite-difference columns go in one batched call)."""
        nonlocal evaluations
        columns = np.asarray(x, float).reshape(len(names), -1).T
        evaluations += len(columns)
        values, _ = train([module.space.from_vector(column) for column in columns])
        return values[0] if np.ndim(x) == 1 else values.T

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
    low, high = found.get_bounds()
    jacobian, _ = minimize.jacobian_fd(
        residual=residuals,
        x=x.reshape(-1, 1),
        r=at_optimum.reshape(-1, 1),
        eps=h.diff_step,
        n_res=0,
        bounds=[low.reshape(-1, 1), high.reshape(-1, 1)],
    )
    covariance, interval = sysid.calculate_intervals([at_optimum], jacobian, alpha=1.0 - h.confidence)
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
