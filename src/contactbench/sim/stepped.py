"""Batched rollouts of engines stepped toss by toss from Python (PyBullet, Drake), spread over worker processes."""

from __future__ import annotations

import logging
import multiprocessing
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.recordings import Scene
from contactbench.sim.mujoco_scene import body_frame_velocities
from contactbench.sim.rollout import Rollouts, SimulationResult, available_cores, unstable_frames

log = logging.getLogger(__name__)


class World(ABC):
    """One engine world of a scene, reused toss after toss; each worker process holds one."""

    @abstractmethod
    def toss(
        self, parameters: Any, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Frames 1..n_steps after poses0 [K, 7] / velocities0 [K, 6] (world frame): poses [n_steps, K, 7] and world
        velocities [n_steps, K, 6]; NaN from a frame where the engine failed. Nothing of an earlier toss carries
        over."""

    def close(self) -> None:  # noqa: B027 (worlds without native handles have nothing to release)
        """Release the engine's resources."""


WorldFactory = Callable[[Scene, int], World]  # (scene, substeps) -> World; picklable (a module-level class or function)

_world: World | None = None  # the worker process's own world


def _start_worker(factory: WorldFactory, scene: Scene, substeps: int) -> None:
    global _world
    _world = factory(scene, substeps)


def _toss_chunk(items: list[tuple[Any, np.ndarray, np.ndarray]], n_steps: int) -> tuple[np.ndarray, np.ndarray]:
    return toss_all(_world, items, n_steps)


def toss_all(
    world: World, items: Sequence[tuple[Any, np.ndarray, np.ndarray]], n_steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """(parameters, poses0, velocities0) items -> poses [M, n_steps, K, 7], velocities [M, n_steps, K, 6]; an item
    the engine refuses (an exception: an unstable or invalid candidate) is all NaN, never a crash mid-search."""
    poses, velocities = [], []
    for parameters, poses0, velocities0 in items:
        try:
            p, v = world.toss(parameters, poses0, velocities0, n_steps)
        except Exception as error:  # noqa: BLE001 (any engine error makes this one candidate unusable, not the search)
            log.debug("toss failed in %s: %s", type(world).__name__, error)
            k = len(poses0)
            p, v = np.full((n_steps, k, 7), np.nan), np.full((n_steps, k, 6), np.nan)
        poses.append(p)
        velocities.append(v)
    return np.stack(poses), np.stack(velocities)


def worker_context() -> multiprocessing.context.BaseContext:
    """Workers never fork the caller, which may hold threads (torch, Hydra launchers): a fork server, else spawn."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    return multiprocessing.get_context("forkserver")


class SteppedRollouts(Rollouts):
    """Rolls B parameter sets x N tosses out in `nthread` worker processes (one: in this process), each with its own
    world; the results are judged for stability exactly as MuJoCo's are (sim/rollout.unstable_frames)."""

    def __init__(self, dataset: Scene, factory: WorldFactory, nthread: int | None = None, substeps: int = 1):
        self.dataset = dataset
        self.factory = factory
        self.substeps = int(substeps)
        self.nthread = int(nthread or available_cores())
        self._pool: ProcessPoolExecutor | None = None
        self._local: World | None = None

    def simulate(self, params, poses0: np.ndarray, velocities0: np.ndarray, n_steps: int) -> SimulationResult:
        parameter_sets = list(params) if isinstance(params, (list, tuple)) else [params]
        poses0 = np.asarray(poses0, dtype=np.float64)
        velocities0 = np.asarray(velocities0, dtype=np.float64)
        n, k = poses0.shape[:2]
        items = [(p, poses0[i], velocities0[i]) for p in parameter_sets for i in range(n)]
        shape = (len(parameter_sets), n, n_steps, k)
        if not items or n_steps == 0:
            poses, velocities = np.empty(shape + (7,)), np.empty(shape + (6,))
        else:
            poses, velocities = self._run(items, n_steps)
            poses, velocities = poses.reshape(shape + (7,)), velocities.reshape(shape + (6,))
        diverged = np.maximum.accumulate(
            ~(np.isfinite(poses).all(axis=(-1, -2)) & np.isfinite(velocities).all(axis=(-1, -2))), axis=-1
        )
        poses[diverged] = np.nan
        velocities[diverged] = np.nan
        qvel = body_frame_velocities(poses, velocities)
        return SimulationResult(poses, qvel, unstable_frames(self.dataset, poses, qvel, poses0, velocities0, diverged))

    def _run(self, items: list, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        if self._local is None:  # built here first: a scene the engine refuses is one clear error, not a dead worker
            try:
                self._local = self.factory(self.dataset, self.substeps)
            except Exception as error:  # noqa: BLE001 (whatever the engine raises, the message names the scene)
                where = self.dataset.root / "meta.json" if self.dataset.root is not None else self.dataset.name
                raise ContactbenchError(
                    f"{where}: {self.factory.__name__} cannot build this scene ({type(error).__name__}: "
                    f"{str(error).strip().splitlines()[0] if str(error).strip() else 'no message'})"
                ) from error
        if self.nthread == 1 or len(items) == 1:
            return toss_all(self._local, items, n_steps)
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                self.nthread,
                mp_context=worker_context(),
                initializer=_start_worker,
                initargs=(self.factory, self.dataset, self.substeps),
            )
        chunks = [list(chunk) for chunk in np.array_split(np.arange(len(items)), self.nthread) if len(chunk)]
        futures = [self._pool.submit(_toss_chunk, [items[i] for i in chunk], n_steps) for chunk in chunks]
        parts = [future.result() for future in futures]
        return np.concatenate([p for p, _ in parts]), np.concatenate([v for _, v in parts])

    def renew_data(self) -> None:
        """After a timed-out call: its workers may be stuck in native code, so they are ended, not waited for."""
        if self._pool is not None:
            processes = list(self._pool._processes.values())  # before shutdown, which forgets them
            self._pool.shutdown(wait=False, cancel_futures=True)
            for process in processes:
                process.terminate()
            self._pool = None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._local is not None:
            self._local.close()
            self._local = None
