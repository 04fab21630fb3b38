"""Batched MuJoCo rollouts of a recordings scene: many parameter sets x many trajectories in one native call.

State vectors are MuJoCo's `mjSTATE_FULLPHYSICS` layout, nstate = mj_stateSize(model, mjSTATE_FULLPHYSICS):
[time, qpos (7 per body: x y z qw qx qy qz), qvel (6 per body: world linear, body angular)]; the scenes have no
actuators or plugins, so act and plugin state are empty (checked).
"""

from __future__ import annotations

import logging
import os
import threading
from abc import ABC, abstractmethod
from collections import Counter, OrderedDict
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import mujoco
import mujoco.rollout
import numpy as np

from contactbench import rotations
from contactbench.protocol import Context
from contactbench.scene import Scene
from contactbench.sim.mujoco_scene import (
    NO_EFFECTS,
    ContactParameters,
    SceneEffects,
    StateLayout,
    body_frame_velocities,
    build_model,
    inertials,
    world_velocities,
)

log = logging.getLogger(__name__)
FULL_PHYSICS = mujoco.mjtState.mjSTATE_FULLPHYSICS
# MuJoCo prints every solver warning to stdout (a search can print millions of "Linesearch objective is not
# convex"); during our rollouts they are counted instead and the first of each kind is logged. Divergence itself is
# detected from the states.
WARNINGS: Counter[str] = Counter()


def _count_warning(message: str) -> None:
    WARNINGS[message] += 1
    if WARNINGS[message] == 1:
        log.debug("MuJoCo: %s (further ones counted in contactbench.sim.rollout.WARNINGS)", message.strip())


_hook_lock = threading.Lock()
_hook_users = 0
_hook_previous = None


@contextmanager
def counted_warnings() -> Iterator[None]:
    """MuJoCo's warnings go to WARNINGS while any caller is inside (rollouts may overlap: a timed-out one runs on);
    the process's previous warning hook is restored when the last one leaves. Importing installs nothing."""
    global _hook_users, _hook_previous
    with _hook_lock:
        if _hook_users == 0:
            _hook_previous = mujoco.get_mju_user_warning()
            mujoco.set_mju_user_warning(_count_warning)
        _hook_users += 1
    try:
        yield
    finally:
        with _hook_lock:
            _hook_users -= 1
            if _hook_users == 0:
                mujoco.set_mju_user_warning(_hook_previous)
                _hook_previous = None


# MuJoCo answers a NaN/huge state by resetting the data, which zeroes its time; starting every rollout at a
# non-zero time makes such a reset visible in the returned states.
START_TIME = 1.0
# Contacts and semi-implicit Euler only dissipate, so an item whose mechanical energy climbs above
# ENERGY_GAIN x its initial energy (+ ENERGY_SLACK per kg, for soft-contact springs) has blown up.
ENERGY_GAIN = 2.0
ENERGY_SLACK = 1e-2  # J/kg
MODEL_CACHE_SIZE = 512


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the platform reports one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def state_offset(model: mujoco.MjModel, component: mujoco.mjtState) -> int:
    """Where `component` starts inside a full-physics state (mj_getState writes components in bit order)."""
    return mujoco.mj_stateSize(model, int(FULL_PHYSICS) & (int(component) - 1))


@dataclass(frozen=True)
class SimulationResult:
    """Simulated frames for B parameter sets x N initial states, and which items blew up."""

    poses: np.ndarray  # [B, N, T, K, 7] recordings poses; NaN from the frame where MuJoCo diverged and reset
    qvel: np.ndarray  # [B, N, T, K, 6] MuJoCo free-joint velocities: world linear (mesh-frame origin), BODY angular
    unstable_frames: (
        np.ndarray
    )  # [B, N, T] diverged (MuJoCo reset), gained energy (ENERGY_GAIN) or fell through the floor

    @property
    def unstable(self) -> np.ndarray:
        """[B, N] items unstable at any frame."""
        return self.unstable_frames.any(axis=-1)

    @cached_property
    def velocities(self) -> np.ndarray:
        """[B, N, T, K, 6] world-frame linear and angular velocity (the recordings convention), made on first use."""
        return world_velocities(self.poses, self.qvel)


class Rollouts(ABC):
    """Batched simulation of a scene for many parameter sets x initial states, in any engine (sim/engines.py)."""

    dataset: Scene

    @abstractmethod
    def simulate(self, params, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int) -> SimulationResult:
        """Frames 1..n_steps (dt apart) after poses0 [N, K, 7] / velocities0 [N, K, 6], for B parameter sets (one set:
        B = 1)."""

    def check(self, params) -> None:  # noqa: B027 (engines whose parameters validate themselves check nothing more)
        """Raise for a parameter set the engine refuses before any rollout (MuJoCo: one that does not compile)."""

    def renew_data(self) -> None:  # noqa: B027 (engines without per-call state have nothing to renew)
        """Start afresh after a call that timed out (its native work may still be running)."""

    def close(self) -> None:  # noqa: B027 (engines without workers have nothing to close)
        """Release worker processes or native resources."""

    def rollout_context(self, context: Context, params) -> SimulationResult:
        """The shared protocol: start from the last context frame, return context + predictions [B, N, horizon, ...]."""
        result = self.simulate(
            params, context.poses[:, -1], context.velocities[:, -1], context.horizon - context.n_context
        )
        leading = result.poses.shape[:1]
        context_qvel = body_frame_velocities(context.poses, context.velocities)
        return SimulationResult(
            np.concatenate([np.broadcast_to(context.poses, leading + context.poses.shape), result.poses], axis=2),
            np.concatenate([np.broadcast_to(context_qvel, leading + context_qvel.shape), result.qvel], axis=2),
            np.concatenate([np.zeros(leading + context.poses.shape[:2], dtype=bool), result.unstable_frames], axis=2),
        )


class MujocoRollouts(Rollouts):
    """Rolls a dataset's scene out in MuJoCo for any number of contact parameter sets and initial states."""

    def __init__(self, dataset: Scene, nthread: int | None = None, substeps: int = 1):
        self.dataset = dataset
        self.substeps = int(substeps)
        self.nthread = int(nthread or available_cores())
        self._models: OrderedDict[ContactParameters, mujoco.MjModel] = OrderedDict()
        reference = self.model(ContactParameters.mujoco_default(dataset.n_bodies))
        self.timestep = reference.opt.timestep
        self.nstate = mujoco.mj_stateSize(reference, FULL_PHYSICS)
        qpos_at = state_offset(reference, mujoco.mjtState.mjSTATE_QPOS)
        qvel_at = state_offset(reference, mujoco.mjtState.mjSTATE_QVEL)
        self._qpos = slice(qpos_at, qpos_at + reference.nq)
        self._qvel = slice(qvel_at, qvel_at + reference.nv)
        if self.nstate != 1 + reference.nq + reference.nv:
            raise ValueError(
                f"scene has {self.nstate - 1 - reference.nq - reference.nv} unexpected state entries (act/plugin)"
            )
        self.layout = StateLayout.of(dataset, reference)
        self._data = [mujoco.MjData(reference) for _ in range(self.nthread)]
        self._reference_key = structure_key(reference)
        self._other_data: dict[tuple, list[mujoco.MjData]] = {}
        self._persistent_pool = True

    def renew_data(self) -> None:
        """Fresh MjData for every thread (after a timed-out call, whose native threads may still hold the old ones)."""
        self._data = [mujoco.MjData(self._data[0].model) for _ in range(self.nthread)]
        self._other_data.clear()
        # The shared persistent pool may still be busy with the abandoned call: use fresh threads from now on.
        self._persistent_pool = False

    def _data_for(self, key: tuple, model: mujoco.MjModel) -> list[mujoco.MjData]:
        """Per-thread MjData that fit models of this structure (the reference's, or made once per structure)."""
        if key == self._reference_key:
            return self._data
        if key not in self._other_data:
            self._other_data[key] = [mujoco.MjData(model) for _ in range(self.nthread)]
        return self._other_data[key]

    def check(self, params: ContactParameters) -> None:
        self.model(params)

    def model(self, params: ContactParameters) -> mujoco.MjModel:
        """The compiled scene for `params`, cached (least recently used go first) for repeated parameter sets."""
        if params in self._models:
            self._models.move_to_end(params)
            return self._models[params]
        model = build_model(self.dataset, params, self.substeps)
        self._models[params] = model
        if len(self._models) > MODEL_CACHE_SIZE:
            self._models.popitem(last=False)
        return model

    def initial_states(self, poses: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Full-physics states [N, nstate] from recordings poses [N, K, 7] and world velocities [N, K, 6]."""
        qpos, qvel = self.layout.pack(np.asarray(poses, dtype=np.float64), np.asarray(velocities, dtype=np.float64))
        states = np.zeros((len(qpos), self.nstate))
        states[:, 0] = START_TIME
        states[:, self._qpos] = qpos
        states[:, self._qvel] = qvel
        return states

    def simulate(
        self,
        params: ContactParameters | Sequence[ContactParameters],
        poses0: np.ndarray,
        velocities0: np.ndarray,
        n_steps: int,
    ) -> SimulationResult:
        """Frames 1..n_steps (dt apart) after poses0 [N, K, 7] / velocities0 [N, K, 6], for B parameter sets.

        All B x N rollouts go to MuJoCo in one call, spread over the threads; a single parameter set gives B = 1.
        """
        parameter_sets = [params] if isinstance(params, ContactParameters) else list(params)
        models = [self.model(p) for p in parameter_sets]
        initial = self.initial_states(poses0, velocities0)
        n_batch = len(models) * len(initial)
        n_substeps = n_steps * self.substeps
        states = np.empty((n_batch, n_substeps, self.nstate))
        if n_batch and n_substeps:
            # One native call per group of structurally alike models (usually one group: all of them).
            groups: dict[tuple, list[int]] = {}
            for index, model in enumerate(models):
                groups.setdefault(structure_key(model), []).append(index)
            with counted_warnings():
                for key, members in groups.items():
                    rows = np.concatenate([np.arange(i * len(initial), (i + 1) * len(initial)) for i in members])
                    out = states if len(groups) == 1 else np.empty((len(rows), n_substeps, self.nstate))
                    mujoco.rollout.rollout(
                        [models[i] for i in members for _ in range(len(initial))],
                        self._data_for(key, models[members[0]]),
                        np.tile(initial, (len(members), 1)),
                        nstep=n_substeps,
                        state=out,
                        persistent_pool=self._persistent_pool,
                    )
                    if len(groups) > 1:
                        states[rows] = out
        frames = states[:, self.substeps - 1 :: self.substeps]
        if self.substeps > 1:  # keep the returned frames, not every substep, alive
            frames = np.ascontiguousarray(frames)
        frames = frames.reshape(len(models), len(initial), n_steps, self.nstate)
        # Views into the state buffer: copying them out cost a noticeable share of the stepping time.
        poses, qvel = self.layout.unpack(frames[..., self._qpos], frames[..., self._qvel])
        expected_time = START_TIME + self.timestep * self.substeps * np.arange(1, n_steps + 1)
        diverged = np.maximum.accumulate(np.abs(frames[..., 0] - expected_time) > self.timestep / 2, axis=-1)
        poses[diverged] = np.nan
        qvel[diverged] = np.nan
        effects = [p.effects for p in parameter_sets]
        return SimulationResult(
            poses, qvel, unstable_frames(self.dataset, poses, qvel, poses0, velocities0, diverged, effects)
        )

    def step(
        self, params: ContactParameters, qpos: np.ndarray, qvel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame (dt: `substeps` MuJoCo steps) after N free-joint states qpos [N, nq], qvel [N, nv], in one native
        call for all N: the new qpos and qvel, NaN where MuJoCo diverged, and those items [N].

        A closed loop (a learned correction between frames) steps frame by frame: each call starts MuJoCo's solver
        cold, where a long rollout warm-starts it from the previous step; on the real cube the two differed by under
        1e-5 m over a whole toss."""
        model = self.model(params)
        states = np.zeros((len(qpos), self.nstate))
        states[:, 0] = START_TIME
        states[:, self._qpos] = qpos
        states[:, self._qvel] = qvel
        out = np.empty((len(states), self.substeps, self.nstate))
        if len(states):
            with counted_warnings():
                mujoco.rollout.rollout(
                    model,
                    self._data_for(structure_key(model), model),
                    states,
                    nstep=self.substeps,
                    state=out,
                    persistent_pool=self._persistent_pool,
                    # One share per thread: one frame costs about the same for every item, and MuJoCo's default of
                    # ten shares per thread made the call slower (how items are shared changes no number).
                    chunk_size=-(-len(states) // self.nthread),
                )
        last = out[:, -1]
        diverged = np.abs(last[:, 0] - (START_TIME + self.timestep * self.substeps)) > self.timestep / 2
        new_qpos, new_qvel = last[:, self._qpos].copy(), last[:, self._qvel].copy()
        new_qpos[diverged] = np.nan
        new_qvel[diverged] = np.nan
        return new_qpos, new_qvel, diverged


def unstable_frames(
    dataset: Scene,
    poses: np.ndarray,
    qvel: np.ndarray,
    poses0: np.ndarray,
    velocities0: np.ndarray,
    diverged: np.ndarray,
    effects: Sequence[SceneEffects] | None = None,
) -> np.ndarray:
    """[B, N, T] frames from which a simulation is unusable: it diverged (`diverged` [B, N, T]: the engine failed or
    left the finite numbers), gained energy (ENERGY_GAIN) or fell through the floor; poses [B, N, T, K, 7] and
    free-joint velocities qvel [B, N, T, K, 6] started from poses0 [N, K, 7] / velocities0 [N, K, 6], each of the B
    parameter sets with its own `effects` (None: NO_EFFECTS for all)."""
    effects = [NO_EFFECTS] * len(poses) if effects is None else list(effects)
    # Each parameter set's energy with its own mass properties and gravity: measured with the recordings' ones, an
    # offset centre of mass gains "energy" in free flight and a correct model reads as blown up. Sets that share
    # their effects (all of a SysID generation) are measured in one pass.
    by_effects: dict[SceneEffects, list[int]] = {}
    for b, scene_effects in enumerate(effects):
        by_effects.setdefault(scene_effects, []).append(b)
    masses = sum(body.mass for body in dataset.bodies)
    gained = np.empty(poses.shape[:3], dtype=bool)
    with np.errstate(invalid="ignore", over="ignore"):
        for scene_effects, members in by_effects.items():
            chosen = slice(None) if len(by_effects) == 1 else members
            energy = body_frame_energy(dataset, poses[chosen], qvel[chosen], scene_effects)
            initial = mechanical_energy(
                dataset, np.asarray(poses0, dtype=np.float64), np.asarray(velocities0, dtype=np.float64), scene_effects
            )
            allowed = ENERGY_GAIN * initial + ENERGY_SLACK * masses
            # Non-finite energy only flags frames that diverged (NaN) anyway.
            gained[chosen] = ~(energy <= allowed[:, None])
        # A body whose frame origin is lower than this under the floor has no vertex above it.
        sunk_depth = np.array(
            [np.linalg.norm(dataset.body_mesh(k).vertices, axis=1).max() for k in range(dataset.n_bodies)]
        )
        sunk = (poses[..., 2] < dataset.floor_z - sunk_depth).any(axis=-1)
    return np.maximum.accumulate(diverged | gained | sunk, axis=-1)


def structure_key(model: mujoco.MjModel) -> tuple:
    """What MjData's layout depends on beyond the sizes: a body whose centre of mass leaves its frame origin (an
    offset centre of mass) is no longer "simple", and MuJoCo then needs other sparse-matrix space; stepping such a
    model with data made for a simple one returns NaN."""
    return (int(model.nC), tuple(model.body_simple.tolist()), tuple(model.dof_simplenum.tolist()))


def mechanical_energy(
    dataset: Scene, poses: np.ndarray, velocities: np.ndarray, effects: SceneEffects = NO_EFFECTS
) -> np.ndarray:
    """Kinetic + gravitational energy (J, zero at the floor) of the scene with `effects` at poses [..., K, 7],
    velocities [..., K, 6]."""
    return body_frame_energy(dataset, poses, body_frame_velocities(poses, velocities), effects)


def body_frame_energy(
    dataset: Scene, poses: np.ndarray, qvel: np.ndarray, effects: SceneEffects = NO_EFFECTS
) -> np.ndarray:
    """mechanical_energy from MuJoCo's free-joint velocities qvel [..., K, 6] (angular part in the body frame)."""
    masses = np.array([body.mass for body in dataset.bodies])
    com, inertia = inertials(dataset, effects)
    position = poses[..., :3]
    if np.any(com):
        position = position + rotations.rotate(poses[..., 3:], com)
    height = (position - np.array([0.0, 0.0, dataset.floor_z])) @ (np.asarray(dataset.gravity) * effects.gravity_scale)
    kinetic = kinetic_energies(masses, com, inertia, poses, qvel).sum(axis=-1)
    return kinetic - np.einsum("k,...k->...", masses, height)


def kinetic_energies(
    masses: np.ndarray, com: np.ndarray, inertia: np.ndarray, poses: np.ndarray, qvel: np.ndarray
) -> np.ndarray:
    """[..., K] each body's kinetic energy (J) at poses [..., K, 7] with free-joint velocities qvel [..., K, 6]; masses
    [K], centres of mass [K, 3] (mesh frame) and inertias about them [K, 3, 3]."""
    linear, angular = qvel[..., :3], qvel[..., 3:]
    if np.any(com):  # meshes written about their centre of mass need no rotation here
        linear = linear + rotations.rotate(poses[..., 3:], np.cross(angular, com))
    translational = np.einsum("k,...ki,...ki->...k", masses, linear, linear)
    rotational = np.einsum("...ki,kij,...kj->...k", angular, inertia, angular)
    return 0.5 * (translational + rotational)


def rollout_context(
    dataset: Scene, context: Context, params: ContactParameters, substeps: int = 1, nthread: int | None = None
) -> np.ndarray:
    """Poses [N, context.horizon, K, 7]: the context frames, then MuJoCo's prediction from the last of them."""
    return MujocoRollouts(dataset, nthread, substeps).rollout_context(context, params).poses[0]
