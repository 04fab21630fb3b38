"""Batched rollouts of engines stepped toss by toss from Python (PyBullet, Drake), spread over worker processes.

A worker process that dies in native code (a segmentation fault or an abort in the engine) costs only the toss it was
running: each worker is a pool of its own (a "lane"), which takes a world that may crash its tosses one task each, so
a crash breaks no other worker's futures and no finished toss; the dead lane's tosses go on in a fresh process, where
a toss that keeps killing fresh processes of its own is unstable (NaN), exactly as a toss whose engine raised, and
every other toss gets the numbers it gets in any process."""

from __future__ import annotations

import logging
import multiprocessing
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from concurrent.futures import CancelledError, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np

from contactbench.errors import ContactbenchError
from contactbench.processes import standard_start_method
from contactbench.scene import Scene
from contactbench.sim.mujoco_scene import body_frame_velocities
from contactbench.sim.rollout import Rollouts, SimulationResult, available_cores, unstable_frames

log = logging.getLogger(__name__)

# Fresh processes a toss may kill, as the first toss in each, before it counts as unstable: drake 1.51.1 crashed at
# random even there, and ran the same toss through when run again.
FRESH_TRIES = 3
CRASH_PRONE_TASK_TOSSES = 32  # tosses per task for a world that may crash its process (World.in_process False)
Item = tuple[Any, np.ndarray, np.ndarray]  # (parameters, poses0 [K, 7], velocities0 [K, 6]) of one toss


class World(ABC):
    """One engine world of a scene, reused toss after toss; each worker process holds one."""

    # False for an engine that may kill its process in native code: its tosses then always run in worker processes,
    # never in the caller's (a search would die with it).
    in_process: bool = True

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


def _toss_chunk(items: list[Item], n_steps: int) -> tuple[np.ndarray, np.ndarray]:
    return toss_all(_world, items, n_steps)


def _started() -> bool:
    """A fresh lane's first task: its worker process started and built its world."""
    return _world is not None


def toss_all(world: World, items: Sequence[Item], n_steps: int) -> tuple[np.ndarray, np.ndarray]:
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
    standard_start_method()
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    return multiprocessing.get_context("forkserver")


def _end(pool: ProcessPoolExecutor) -> None:
    """Shut a lane down without waiting: its process may be stuck in native code (a timed-out call), so it is
    terminated."""
    processes = list((pool._processes or {}).values())  # before shutdown, which forgets them
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()


class SteppedRollouts(Rollouts):
    """Rolls B parameter sets x N tosses out in `nthread` worker processes (one: in this process, unless the world
    says it may crash it), each with its own world; the results are judged for stability exactly as MuJoCo's are
    (sim/rollout.unstable_frames)."""

    def __init__(self, dataset: Scene, factory: WorldFactory, nthread: int | None = None, substeps: int = 1):
        self.dataset = dataset
        self.factory = factory
        self.substeps = int(substeps)
        self.nthread = int(nthread or available_cores())
        self._lanes: list[ProcessPoolExecutor | None] = [None] * self.nthread  # one worker process each
        self._local: World | None = None
        self._generation = 0  # renew_data calls: a call abandoned by a timeout neither retries nor replaces lanes

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

    def _new_lane(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            1,
            mp_context=worker_context(),
            initializer=_start_worker,
            initargs=(self.factory, self.dataset, self.substeps),
        )

    def _run(self, items: list[Item], n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        if self._local is None:  # built here first: a scene the engine refuses is one clear error, not a dead worker
            try:
                self._local = self.factory(self.dataset, self.substeps)
            except Exception as error:  # noqa: BLE001 (whatever the engine raises, the message names the scene)
                where = self.dataset.root / "meta.json" if self.dataset.root is not None else self.dataset.name
                raise ContactbenchError(
                    f"{where}: {self.factory.__name__} cannot build this scene ({type(error).__name__}: "
                    f"{str(error).strip().splitlines()[0] if str(error).strip() else 'no message'})"
                ) from error
        if (self.nthread == 1 or len(items) == 1) and self._local.in_process:
            return toss_all(self._local, items, n_steps)
        return self._toss_in_lanes(items, n_steps)

    def _toss_in_lanes(self, items: list[Item], n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        """The items in contiguous chunks over the lanes: a world that may crash gets one task per toss, another one
        task per chunk until a crash. A lane runs its tasks in order, so the first unfinished task of a lane whose
        process died is the one that killed it: the lane's finished tasks keep their results, and the rest of its
        chunk goes on in a fresh lane, one task per toss, the killer first (a crash may build up over many tosses, or
        strike at random). A toss that has killed FRESH_TRIES fresh processes, as the first toss in each, stays NaN
        (unstable); so do the tosses of a fresh lane that dies before its first toss (it cannot even start, and
        retrying cannot help)."""
        generation = self._generation
        k = len(items[0][1])
        poses, velocities = np.full((len(items), n_steps, k, 7), np.nan), np.full((len(items), n_steps, k, 6), np.nan)
        chunks = [chunk.tolist() for chunk in np.array_split(np.arange(len(items)), self.nthread) if len(chunk)]
        queues = dict(enumerate(chunks))
        # Tosses per task: a world that may crash its process sends a few at a time (a crash then costs the task's
        # unfinished tosses, run again one per task to find the one that crashed; one toss per task costs its
        # inter-process round trip on every toss, which outweighs a short toss's own simulation).
        batch = len(items) if self._local.in_process else CRASH_PRONE_TASK_TOSSES
        fresh_kills = dict.fromkeys(range(len(items)), 0)
        while queues and self._generation == generation:
            running = []
            for lane, queue in queues.items():
                fresh = self._lanes[lane] is None
                if fresh:
                    self._lanes[lane] = self._new_lane()
                pool = self._lanes[lane]
                tasks = [queue[start : start + batch] for start in range(0, len(queue), batch)]
                try:
                    started = pool.submit(_started) if fresh else None
                    futures = [pool.submit(_toss_chunk, [items[i] for i in task], n_steps) for task in tasks]
                except (BrokenProcessPool, RuntimeError, OSError):  # died, or shut down by a timed-out call's renewal
                    started, futures = None, []
                running.append((lane, pool, queue, tasks, started, futures, fresh))
            queues = {}
            for lane, pool, queue, tasks, started, futures, fresh in running:
                try:
                    if not futures:
                        raise BrokenProcessPool("the lane took no tasks")
                    if started is not None:
                        started.result()
                except (BrokenProcessPool, CancelledError):
                    self._drop(lane, pool)
                    if not fresh:  # it died between calls: its chunk goes to a fresh lane
                        queues[lane] = queue
                        continue
                    log.error(
                        "a fresh %s worker process died before its first toss: %d tosses left unstable (NaN)",
                        self.factory.__name__,
                        len(queue),
                    )
                    continue
                done = 0  # tosses of the queue finished
                for task, future in zip(tasks, futures):
                    try:
                        poses[task], velocities[task] = future.result()
                        done += len(task)
                    except (BrokenProcessPool, CancelledError):
                        self._drop(lane, pool)
                        killer = task[0] if len(task) == 1 else None
                        if killer is not None and fresh and done == 0:
                            fresh_kills[killer] += 1
                        given_up = killer is not None and fresh_kills[killer] == FRESH_TRIES
                        log.warning(
                            "a %s worker process died in a toss (a crash in native code); %s",
                            self.factory.__name__,
                            f"the toss killed {FRESH_TRIES} fresh processes: unstable (NaN)"
                            if given_up
                            else "its tosses not done run again in a fresh process",
                        )
                        batch = 1
                        if queue[done + given_up :]:
                            queues[lane] = queue[done + given_up :]
                        break
        return poses, velocities

    def _drop(self, lane: int, pool: ProcessPoolExecutor) -> None:
        """End a lane whose process died (unless a renewal has replaced it already)."""
        if self._lanes[lane] is pool:
            _end(pool)
            self._lanes[lane] = None

    def renew_data(self) -> None:
        """After a timed-out call: its workers may be stuck in native code, so they are ended, not waited for."""
        self._generation += 1
        lanes, self._lanes = self._lanes, [None] * self.nthread
        for pool in lanes:
            if pool is not None:
                _end(pool)

    def close(self) -> None:
        lanes, self._lanes = self._lanes, [None] * self.nthread
        for pool in lanes:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
        if self._local is not None:
            self._local.close()
            self._local = None
