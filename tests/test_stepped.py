"""Rollouts stepped toss by toss in worker processes: a worker killed in native code costs only its own tosses."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from contactbench.protocol import make_context
from contactbench.sim.stepped import SteppedRollouts, World

ABORT = "abort"  # parameters that kill the worker process every time
LATE = "late"  # parameters that kill a worker process that has tossed before (a crash that builds up)


class Crashing(World):
    """Holds each toss at its start, tagged with its parameters; ABORT kills the process as drake 1.51.1's
    segmentation faults do, LATE kills it after other tosses, and a path kills it only while that file does not
    exist (a crash at random, which the same toss survives when run again)."""

    in_process = False

    def __init__(self, scene, substeps):
        self.scene, self.tossed = scene, 0

    def toss(self, parameters, poses0, velocities0, n_steps):
        self.tossed += 1
        if parameters == ABORT or (parameters == LATE and self.tossed > 1):
            os.abort()
        if parameters == LATE:
            parameters = 0.25
        elif isinstance(parameters, str):
            marker, parameters = Path(parameters), 0.25
            if not marker.exists():
                marker.touch()
                os.abort()
        poses = np.repeat(poses0[None], n_steps, axis=0)
        poses[..., 0] += parameters  # the candidate's own result
        return poses, np.zeros((n_steps, *velocities0.shape))


class CrashingRarely(Crashing):
    """The same world, as one that runs in the caller's process with one thread (PyBullet): worker processes get
    their tosses a chunk at a time until one crashes."""

    in_process = True


def start():
    from conftest import falling_cubes  # here, not at the top: each worker process imports this module

    data = falling_cubes(2, 8)
    return data.scene, make_context(data.split("train"), data.dt, 6)


@pytest.mark.parametrize("world", [Crashing, CrashingRarely])
def test_a_crashed_worker_costs_only_its_tosses_and_the_next_call_works(world, tmp_path):
    scene, context = start()
    once = str(tmp_path / "crashed-once")
    rollouts = SteppedRollouts(scene, world, nthread=2)
    try:
        crashed = rollouts.rollout_context(context, [0.5, ABORT, 0.7, once, 0.9, LATE])
        after = rollouts.rollout_context(context, [0.5, 0.7, 0.9])
    finally:
        rollouts.close()
    assert crashed.unstable.tolist() == [[False] * 2, [True] * 2, [False] * 2, [False] * 2, [False] * 2, [False] * 2]
    assert np.isnan(crashed.poses[1, :, 6:]).all()
    # Every other candidate has exactly the numbers it gets in a call where nothing crashed; the tosses that crashed
    # once, or only after others, got their own when run again alone.
    np.testing.assert_array_equal(crashed.poses[[0, 2, 4]], after.poses)
    held = context.poses[None, :, -1:, :, 0] + np.array([0.5, 0.7, 0.9, 0.25])[:, None, None, None]
    np.testing.assert_array_equal(
        after.poses[:, :, 6:, :, 0], np.broadcast_to(held[:3], after.poses[:, :, 6:, :, 0].shape)
    )
    np.testing.assert_array_equal(crashed.poses[[3, 5], :, 6:, :, 0], np.broadcast_to(held[3], (2, 2, 2, 1)))
    assert Path(once).exists()


def test_a_world_that_may_crash_never_runs_in_the_callers_process():
    scene, context = start()
    rollouts = SteppedRollouts(scene, Crashing, nthread=1)
    try:
        alone = rollouts.simulate([ABORT], context.poses[:1, -1], context.velocities[:1, -1], 2)  # one item, one thread
        result = rollouts.rollout_context(context, [ABORT, 0.5])
    finally:
        rollouts.close()
    assert alone.unstable.tolist() == [[True]]
    assert result.unstable.tolist() == [[True] * 2, [False] * 2]
