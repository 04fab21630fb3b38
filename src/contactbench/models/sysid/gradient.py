"""SysID by gradient descent through MuJoCo's differentiable port, MJX (model=sysid_mjx): sysid's parameters, eq. (1).

The same search space, objective and selection as `sysid` (module.py), another optimiser: Adam on short windows of
the train tosses, each simulated in MJX from its recorded state, the gradient of eq. (1) by forward-mode
differentiation (`jax.jacfwd`: MJX's Newton solver runs a `while_loop`, which reverse mode cannot differentiate,
and the parameters are few). Every `val_every` steps the C-MuJoCo val objective, the one `sysid` selects with,
scores the current parameters; the best is kept. MJX detects mesh-plane contacts differently from C MuJoCo (up to 4
contacts where C has 3; docs/DIFFERENTIABLE.md), so MJX gives directions only: never a score. A hinged scene adds
each hinge's damping and friction loss and the links' inertia scale (sim/articulation.py) to the search; a scene
MJX's put_model refuses is NotApplicable (sim/mjx.py: require_mjx).

With `window_frames: null` the windows are whole tosses from their context (the val objective's rollouts);
`truncation: N` then cuts the gradient's path through the state every N frames (sim/mjx.py: truncated).

The parameters are searched in box coordinates: each is lo + (hi - lo) * sigmoid(u) (the stiffness in log space),
so every step stays inside Table 2c's domain, and the search starts where NGOpt's does (the domain's centre,
damping 50; an articulation dimension a little inside its bound: inside_start).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pytorch_lightning as pl
import torch

from contactbench.errors import ContactbenchError, require_positive_integers
from contactbench.models.sysid.module import IdentifiedModule, fixed_subset, package_versions, save_last_checkpoint
from contactbench.models.sysid.search_space import SearchSpace
from contactbench.protocol import make_context
from contactbench.scene import Recordings, Split
from contactbench.sim import articulation
from contactbench.sim.engines import Dimension
from contactbench.sim.mjx import import_mjx, inertia_constants, pose_loss, require_mjx, truncated
from contactbench.sim.mujoco_scene import StateLayout, build_model

log = logging.getLogger(__name__)

ADAM_BETAS = (0.9, 0.999)
# The fraction of an articulation dimension's range its start keeps from either bound (inside_start); the floor
# damping's start (50 of 0-1000) sits as far inside its own range.
START_MARGIN = 0.05


def decayed(lr: float, step: int, steps: int) -> float:
    """A cosine from lr down to a tenth of it over the steps: window gradients are noisy, late steps settle."""
    return lr * (0.1 + 0.45 * (1 + np.cos(np.pi * step / max(steps, 1))))


def adam_step(
    coordinates: np.ndarray, moments: tuple[np.ndarray, np.ndarray], gradient: np.ndarray, lr: float, step: int
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Adam's update of coordinates at (0-based) step `step`: the new coordinates and first and second moments."""
    beta1, beta2 = ADAM_BETAS
    first = beta1 * moments[0] + (1 - beta1) * gradient
    second = beta2 * moments[1] + (1 - beta2) * gradient**2
    corrected = first / (1 - beta1 ** (step + 1)), second / (1 - beta2 ** (step + 1))
    return coordinates - lr * corrected[0] / (np.sqrt(corrected[1]) + 1e-8), (first, second)


class BoxCoordinates:
    """SearchSpace vectors (per-object friction, floor friction, stiffness, damping, then a hinged scene's joint
    dampings, joint frictions and inertia scale) <-> unbounded coordinates u."""

    def __init__(self, space: SearchSpace):
        k = space.n_bodies
        hinges = articulation.dimensions(space.n_joints)
        self.low = np.array(
            [space.friction[0]] * (k + 1)
            + [np.log(space.stiffness[0]), space.damping[0]]
            + [np.log(d.low) if d.log else d.low for d in hinges]
        )
        self.high = np.array(
            [space.friction[1]] * (k + 1)
            + [np.log(space.stiffness[1]), space.damping[1]]
            + [np.log(d.high) if d.log else d.high for d in hinges]
        )
        self.logarithmic = np.array([i == k + 1 for i in range(k + 3)] + [d.log for d in hinges], dtype=bool)
        self.start = self.to_coordinates(
            np.array(
                [np.mean(space.friction)] * (k + 1)
                + [np.sqrt(np.prod(space.stiffness)), space.initial_damping]
                + [inside_start(d) for d in hinges]
            )
        )

    def to_vector(self, coordinates, xp=np):
        """The search-space vector of coordinates (numpy or jax.numpy arrays, `xp` the module)."""
        inside = self.low + (self.high - self.low) / (1 + xp.exp(-coordinates))
        return xp.where(self.logarithmic, xp.exp(inside), inside)

    def to_coordinates(self, vector: np.ndarray) -> np.ndarray:
        inside = np.where(self.logarithmic, np.log(vector), vector)
        fraction = np.clip((inside - self.low) / (self.high - self.low), 1e-9, 1 - 1e-9)
        return np.log(fraction / (1 - fraction))


def inside_start(dimension: Dimension) -> float:
    """Where the descent starts in an articulation dimension: NGOpt's start (its init), moved at least START_MARGIN of
    the range inside it. A sigmoid passes no gradient at its bounds, and joint damping and friction start at 0."""
    if dimension.log:
        low, high, init = np.log([dimension.low, dimension.high, dimension.init])
    else:
        low, high, init = dimension.low, dimension.high, dimension.init
    margin = START_MARGIN * (high - low)
    start = float(np.clip(init, low + margin, high - margin))
    return float(np.exp(start)) if dimension.log else start


class MjxWindows:
    """Eq. (1) over windows of recorded tosses simulated in MJX, and its gradient in box coordinates (jit once)."""

    def __init__(
        self,
        dataset: Recordings,
        space: SearchSpace,
        context_frames: int,
        window_frames: int | None,
        position_exponent: int,
        substeps: int = 1,
        truncation: int | None = None,
    ):
        jax, jnp, mjx = import_mjx()
        self.jax, self.jnp = jax, jnp
        self.coordinates = BoxCoordinates(space)
        self.context_frames, self.window_frames, self.substeps = context_frames, window_frames, substeps
        # whole tosses: every frame after the context, each toss scored on its own frames (the val objective's form)
        horizon = window_frames or dataset.split("train").n_frames - context_frames
        start = space.from_vector(self.coordinates.to_vector(self.coordinates.start))
        model = build_model(dataset.scene, start, substeps)
        self.layout = StateLayout.of(dataset.scene, model)
        simulated = parametrized(model, mjx.put_model(model), space, self.coordinates, jnp, mjx)
        widths = jnp.asarray(dataset.widths())
        exponent = position_exponent
        bodies = np.array([model.body(f"body{k}").id for k in range(dataset.n_bodies)])
        free = self.layout.free

        def observed(model, data):
            """The frame's poses [K, 7]. A free scene's qpos is its recordings poses; a hinged one's are the bodies'
            frames (body frame = mesh frame), which mjx.step leaves at the step's start: kinematics brings them to
            its end."""
            if free:
                return data.qpos
            data = mjx.kinematics(model, data)
            return jnp.concatenate([data.xpos[bodies], data.xquat[bodies]], axis=-1)

        def rollout(model, qpos, qvel):
            data = mjx.make_data(model).replace(qpos=qpos, qvel=qvel)

            def frame(data, index):
                data = truncated(jax, data, index, truncation)
                data = jax.lax.fori_loop(0, substeps, lambda _, d: mjx.step(model, d), data)
                return data, observed(model, data)

            return jax.lax.scan(frame, data, jnp.arange(horizon))[1]  # [W, 7K] or [W, K, 7]

        def poses(coordinates, qpos, qvel):
            model = simulated(coordinates)
            return jax.vmap(rollout, in_axes=(None, 0, 0))(model, qpos, qvel).reshape(
                len(qpos), horizon, dataset.n_bodies, 7
            )

        def loss(coordinates, qpos, qvel, truth, scored):
            return pose_loss(jnp, poses(coordinates, qpos, qvel), truth, scored, widths, exponent)

        def value_and_gradient(coordinates, qpos, qvel, truth, scored):
            def twice(coordinates):  # the loss as jacfwd's aux too: one primal pass serves both
                value = loss(coordinates, qpos, qvel, truth, scored)
                return value, value

            gradient, value = jax.jacfwd(twice, has_aux=True)(coordinates)
            return value, gradient

        self._value_and_gradient = jax.jit(value_and_gradient)
        self._poses = jax.jit(poses)

    def windows(self, split: Split, dt: float, count: int, rng: np.random.Generator):
        """`count` windows: MJX's initial states (from the context, as the protocol makes them), the recorded frames
        after them and which of those are scored. With window_frames, drawn uniformly from every (toss, start) where
        a context and window_frames frames fit; without, whole tosses (each scored up to its own end)."""
        context = self.context_frames
        if self.window_frames is None:
            tosses = np.sort(rng.choice(split.n_trajectories, size=count, replace=count > split.n_trajectories))
            window = split.select(tosses)
            scored = np.arange(context, split.n_frames)[None, :] < window.lengths[:, None]
        else:
            span = context + self.window_frames
            valid = np.maximum(split.lengths - span + 1, 0)  # starts per toss
            if valid.max() < 1:
                raise ContactbenchError(
                    f"no toss is longer than context_frames + window_frames = {span} frames "
                    "(model.module.window_frames; null: whole tosses)"
                )
            chosen = rng.choice(valid.sum(), size=count, replace=count > valid.sum())
            tosses = np.searchsorted(np.cumsum(valid), chosen, side="right")
            starts = chosen - np.concatenate([[0], np.cumsum(valid)[:-1]])[tosses]
            frames = starts[:, None] + np.arange(span)
            window = Split(
                poses=split.poses[tosses[:, None], frames],
                lengths=np.full(count, span),
                velocities=None if split.velocities is None else split.velocities[tosses[:, None], frames],
            )
            scored = np.ones((count, self.window_frames), dtype=bool)
        initial = make_context(window, dt, context)
        qpos, qvel = self.layout.pack(initial.poses[:, -1], initial.velocities[:, -1])
        truth = np.where(scored[..., None, None], window.poses[:, context:], 0.0)  # frames past the end: unscored
        return qpos, qvel, truth, scored

    def value_and_gradient(self, coordinates: np.ndarray, windows) -> tuple[float, np.ndarray]:
        value, gradient = self._value_and_gradient(self.jnp.asarray(coordinates), *map(self.jnp.asarray, windows))
        return float(value), np.asarray(gradient, dtype=np.float64)

    def poses(self, coordinates: np.ndarray, windows) -> np.ndarray:
        """MJX's poses [W, T, K, 7] over the windows' frames (compiled apart from the gradient, on first use)."""
        qpos, qvel = windows[:2]
        return np.asarray(self._poses(*map(self.jnp.asarray, (coordinates, qpos, qvel))), dtype=np.float64)


def parametrized(model, reference, space: SearchSpace, coordinates: BoxCoordinates, jnp, mjx):
    """coordinates -> the MJX model `reference` (put from the compiled `model`) with those parameters, as
    scene_xml writes them: a pair with the ground (floor, static meshes, height fields) takes max(object, floor)
    friction and the floor's solref, a pair of hinged links the larger of their frictions and MuJoCo's default
    solref, and each geom its body's friction (body-body contacts). A hinged scene also sets each hinge's damping and
    friction loss and scales the links' inertia, with the constants MuJoCo's compiler derives from the inertia."""
    n_bodies, n_joints = space.n_bodies, space.n_joints
    body_of_geom = model.geom_bodyid - 1  # recordings body index (-1: the world's ground geoms)
    first, second = body_of_geom[model.pair_geom1], body_of_geom[model.pair_geom2]
    grounded = np.minimum(first, second) < 0
    pair_body = np.maximum(first, second)
    geom_body = np.maximum(body_of_geom, 0)
    is_body_geom = body_of_geom >= 0
    hinge_dofs = np.array([model.joint(f"hinge{j}").dofadr[0] for j in range(n_joints)], dtype=int)
    reference_scale = space.from_vector(coordinates.to_vector(coordinates.start)).articulation
    reference_scale = 1.0 if reference_scale is None else reference_scale.inertia_scale
    constants = inertia_constants(model, jnp, mjx)

    def simulated(u):
        vector = coordinates.to_vector(u, jnp)
        objects, floor = vector[:n_bodies], vector[n_bodies]
        sliding = jnp.where(
            grounded,
            jnp.maximum(objects[pair_body], floor),
            jnp.maximum(objects[np.maximum(first, 0)], objects[np.maximum(second, 0)]),
        )
        floor_solref = jnp.stack([-vector[n_bodies + 1], -vector[n_bodies + 2]])
        changed = reference.replace(
            pair_friction=reference.pair_friction.at[:, 0].set(sliding).at[:, 1].set(sliding),
            pair_solref=jnp.where(grounded[:, None], floor_solref[None, :], reference.pair_solref),
            geom_friction=reference.geom_friction.at[:, 0].set(
                jnp.where(is_body_geom, objects[geom_body], reference.geom_friction[:, 0])
            ),
        )
        if not n_joints:
            return changed
        hinges = vector[n_bodies + 3 :]
        changed = changed.replace(
            dof_damping=changed.dof_damping.at[hinge_dofs].set(hinges[:n_joints]),
            dof_frictionloss=changed.dof_frictionloss.at[hinge_dofs].set(hinges[n_joints : 2 * n_joints]),
            body_inertia=changed.body_inertia * (hinges[2 * n_joints] / reference_scale),  # the world's is 0
        )
        return changed.replace(**constants(changed))

    return simulated


class GradientSysIDModule(IdentifiedModule):
    """sysid's parameters identified by Adam through MJX; holds the settings and what val selected."""

    model_name = "sysid_mjx"

    def __init__(
        self,
        dataset: Recordings,
        context_frames: int,
        steps: int,
        windows: int,
        window_frames: int | None,
        lr: float,
        val_every: int,
        val_trajectories: int | None,
        seed: int = 0,
        position_exponent: int = 2,
        unstable_penalty: float = 1e3,
        timeout_s: float = 120.0,
        nthread: int | None = None,
        substeps: int = 1,
        engine: str = "mujoco",
        truncation: int | None = None,
    ):
        if engine != "mujoco":
            raise ContactbenchError(f"model.module.engine is {engine!r} (expected mujoco: MJX is MuJoCo's port)")
        require_mjx(dataset.scene)
        super().__init__(dataset, engine)
        require_positive_integers(
            {"steps": steps, "windows": windows, "window_frames": window_frames, "truncation": truncation},
            optional=("window_frames", "truncation"),
        )
        self.save_hyperparameters(ignore=["dataset"], logger=False)

    def fitted_summary(self) -> dict:
        return {
            **super().fitted_summary(),
            "optimizer": {"name": "Adam", "gradients": "jax.jacfwd through MJX"},
            "versions": package_versions("mujoco", "mujoco-mjx", "jax", "jaxlib"),
        }


class AdamThroughMjx(pl.Callback):
    """One Adam step per training step on freshly drawn train windows; val (C MuJoCo) every `val_every` steps and at
    the start and the end, the best kept. The checkpoint holds numbers only: a resumed run draws the same windows
    (seeded by step) and continues exactly."""

    def __init__(self):
        self.step = 0
        self.coordinates: np.ndarray | None = None
        self.moments = (None, None)
        self.best = {"vector": [], "val_loss": float("inf")}
        self.skipped = 0  # steps whose loss or gradient was not finite (left out)
        self.seconds = {"compile": 0.0, "train": 0.0, "val": 0.0}

    def on_fit_start(self, trainer, module: GradientSysIDModule) -> None:
        h = module.hparams
        self.windows = MjxWindows(
            module.dataset,
            module.space,
            h.context_frames,
            h.window_frames,
            h.position_exponent,
            h.substeps,
            h.truncation,
        )
        if self.coordinates is None:
            self.coordinates = self.windows.coordinates.start.copy()
            self.moments = (np.zeros_like(self.coordinates), np.zeros_like(self.coordinates))
        self.rollouts = module.rollouts()
        self.val_objective = module.objective("val", self.rollouts)
        self.train_split = module.dataset.split("train")
        self.compiled = False  # in this process: the first step's time is jax's compile

    def on_fit_end(self, trainer, module) -> None:
        self.val_objective.close()
        self.rollouts.close()

    def on_train_batch_start(self, trainer, module: GradientSysIDModule, batch, batch_index) -> None:
        h = module.hparams
        if self.step >= h.steps:  # a resumed run that had already finished
            trainer.should_stop = True
            return
        if self.step == 0 and not self.best["vector"]:  # the start (NGOpt's) is a candidate too
            self._validate(module)
        rng = np.random.default_rng([h.seed, self.step])
        windows = self.windows.windows(self.train_split, module.dataset.dt, h.windows, rng)
        started = time.perf_counter()
        loss, gradient = self.windows.value_and_gradient(self.coordinates, windows)
        elapsed = time.perf_counter() - started
        self.seconds["train" if self.compiled else "compile"] += elapsed
        self.compiled = True
        if np.isfinite(loss) and np.isfinite(gradient).all():
            lr = decayed(h.lr, self.step, h.steps)
            self.coordinates, self.moments = adam_step(self.coordinates, self.moments, gradient, lr, self.step)
        else:
            self.skipped += 1
        self.step += 1
        module.log_dict(
            {
                "train/loss": loss if np.isfinite(loss) else h.unstable_penalty,
                "train/skipped_steps": float(self.skipped),
                "train/seconds": self.seconds["train"],
                "train/compile_seconds": self.seconds["compile"],
                **{f"params/{k}": float(v) for k, v in self._describe(module).items()},
            },
            on_step=True,
        )
        if self.step % h.val_every == 0 or self.step == h.steps:
            self._validate(module)
        trainer.should_stop = self.step >= h.steps
        save_last_checkpoint(trainer)

    def _parameters(self, module: GradientSysIDModule):
        return module.space.from_vector(self.windows.coordinates.to_vector(self.coordinates))

    def _describe(self, module: GradientSysIDModule) -> dict[str, float]:
        return module.space.describe(self._parameters(module))

    def _validate(self, module: GradientSysIDModule) -> None:
        started = time.perf_counter()
        parameters = self._parameters(module)
        h = module.hparams
        indices = fixed_subset(self.val_objective.n_trajectories, h.val_trajectories, h.seed)
        val_loss = float(self.val_objective([parameters], indices).losses[0])
        self.seconds["val"] += time.perf_counter() - started
        if val_loss < self.best["val_loss"]:
            vector = module.space.to_vector(parameters)
            self.best = {"vector": vector.tolist(), "val_loss": val_loss}
            module.select(vector, val_loss)
        module.log_dict({"val/loss": val_loss, "val/seconds": self.seconds["val"]}, on_step=True)
        log.info("sysid_mjx step %d: val loss %.5f with %s", self.step, val_loss, self._describe(module))

    # ------------------------------------------------------------ checkpointing

    @staticmethod
    def check_state(state: object, where: str) -> None:
        check_descent_state(state, where)

    def state_dict(self) -> dict:
        return {
            "step": self.step,
            "skipped": self.skipped,
            "coordinates": torch.as_tensor(self.coordinates, dtype=torch.float64),
            "first_moment": torch.as_tensor(self.moments[0], dtype=torch.float64),
            "second_moment": torch.as_tensor(self.moments[1], dtype=torch.float64),
            "best_vector": torch.as_tensor(self.best["vector"], dtype=torch.float64),
            "best_val_loss": float(self.best["val_loss"]),
            "seconds": dict(self.seconds),
        }

    def load_state_dict(self, state: dict) -> None:
        check_descent_state(state, "checkpoint descent state")
        self.step, self.skipped = int(state["step"]), int(state["skipped"])
        self.coordinates = state["coordinates"].numpy().copy()
        self.moments = (state["first_moment"].numpy().copy(), state["second_moment"].numpy().copy())
        self.best = {"vector": state["best_vector"].tolist(), "val_loss": float(state["best_val_loss"])}
        self.seconds = {k: float(v) for k, v in state["seconds"].items()}


DESCENT_STATE_FIELDS = (
    "step",
    "skipped",
    "coordinates",
    "first_moment",
    "second_moment",
    "best_vector",
    "best_val_loss",
    "seconds",
)


def check_descent_state(state: object, where: str) -> None:
    """Refuse anything but the numbers-only state AdamThroughMjx.state_dict writes."""

    def fail(field: str, problem: str, expected: str) -> ContactbenchError:
        return ContactbenchError(f"{where}: field '{field}' {problem} (expected {expected})")

    if not isinstance(state, dict):
        raise ContactbenchError(f"{where}: is a {type(state).__name__} (expected a dict of numbers)")
    for name in DESCENT_STATE_FIELDS:
        if name not in state:
            raise fail(name, "is missing", "the numbers-only descent state; resume=false starts over")
    unknown = sorted(set(state) - set(DESCENT_STATE_FIELDS), key=str)
    if unknown:
        raise fail(str(unknown[0]), "is not part of the descent state", f"only {', '.join(DESCENT_STATE_FIELDS)}")
    for name in ("step", "skipped"):
        if isinstance(state[name], bool) or not isinstance(state[name], int) or state[name] < 0:
            raise fail(name, f"is {state[name]!r}", "a non-negative integer")
    size = None
    for name in ("coordinates", "first_moment", "second_moment"):
        value = state[name]
        if not isinstance(value, torch.Tensor) or value.dtype != torch.float64 or value.ndim != 1:
            raise fail(name, f"is a {type(value).__name__}", "a float64 vector")
        if not torch.isfinite(value).all() or (size is not None and len(value) != size):
            raise fail(name, "holds non-finite values or has another length", "finite numbers, one per parameter")
        size = len(value)
    best = state["best_vector"]
    if not isinstance(best, torch.Tensor) or best.dtype != torch.float64 or len(best) not in (0, size):
        raise fail("best_vector", f"is a {type(best).__name__}", f"a float64 vector of {size} parameters")
    if not isinstance(state["best_val_loss"], float):
        raise fail("best_val_loss", f"is {state['best_val_loss']!r}", "a number")
    seconds = state["seconds"]
    if not isinstance(seconds, dict) or set(seconds) != {"compile", "train", "val"}:
        raise fail("seconds", f"is {seconds!r}", "{'compile', 'train', 'val'}: seconds")
    if not all(isinstance(v, float) for v in seconds.values()):
        raise fail("seconds", f"is {seconds!r}", "numbers")
