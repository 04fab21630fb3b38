"""Times MujocoRollouts.simulate against a bare mujoco.rollout.rollout of the same models, states and steps."""

from __future__ import annotations

import argparse
import copy
import time
from dataclasses import replace
from pathlib import Path

import mujoco
import mujoco.rollout
import numpy as np

from contactbench.kinematics import estimate_velocities
from contactbench.recordings import read_recordings
from contactbench.scene import Recordings
from contactbench.sim.mujoco_scene import ContactParameters
from contactbench.sim.rollout import MujocoRollouts, counted_warnings

CUBE_DATA = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"


def parameter_sets(rng: np.random.Generator, count: int, n_bodies: int) -> list[ContactParameters]:
    """Draws from the paper's Table 2c domain (stiffness log-uniform)."""
    return [
        ContactParameters(
            object_friction=rng.uniform(0, 1, n_bodies),
            floor_friction=rng.uniform(0, 1),
            floor_stiffness=10 ** rng.uniform(2, 4),
            floor_damping=rng.uniform(0, 1e3),
        )
        for _ in range(count)
    ]


def first_frames(dataset: Recordings) -> tuple[np.ndarray, np.ndarray]:
    """Poses [N, K, 7] and world velocities [N, K, 6] of every train trajectory's first frame."""
    split = dataset.split("train")
    velocities = split.velocities if split.velocities is not None else estimate_velocities(split.poses, dataset.dt)
    return split.poses[:, 0], velocities[:, 0]


def three_body_scene(
    dataset: Recordings, rng: np.random.Generator, count: int
) -> tuple[Recordings, np.ndarray, np.ndarray]:
    """The first body thrice, started from three recorded tosses side by side and pushed towards each other."""
    meta = copy.deepcopy(dataset.meta)
    meta["bodies"] = [dict(meta["bodies"][0], name=f"body{k}") for k in range(3)]
    scene = replace(dataset, meta=meta)
    poses, velocities = first_frames(dataset)
    picks = rng.integers(0, len(poses), size=(count, 3))
    poses, velocities = poses[picks, 0], velocities[picks, 0]
    offsets = np.array([-1.0, 0.0, 1.0]) * 1.1 * np.linalg.norm(dataset.body_mesh(0).vertices, axis=1).max() * 2
    poses[..., 0] = poses[:, :1, 0] + offsets
    poses[..., 1] = poses[:, :1, 1]
    velocities[..., 0] -= 2.0 * offsets
    return scene, poses, velocities


def measure(name: str, simulator: MujocoRollouts, params, poses0, velocities0, n_steps: int, repeats: int) -> None:
    simulator.simulate(params, poses0, velocities0, n_steps)  # compiles and caches the models
    models = [simulator.model(p) for p in params for _ in range(len(poses0))]
    initial = np.tile(simulator.initial_states(poses0, velocities0), (len(params), 1))
    data = [mujoco.MjData(models[0]) for _ in range(simulator.nthread)]
    nstep = n_steps * simulator.substeps
    wrapped, bare = [], []
    for _ in range(repeats):  # interleaved, so both see the same machine load
        started = time.perf_counter()
        result = simulator.simulate(params, poses0, velocities0, n_steps)
        wrapped.append(time.perf_counter() - started)
        started = time.perf_counter()
        with counted_warnings():  # as simulate does
            mujoco.rollout.rollout(models, data, initial, nstep=nstep, persistent_pool=True)
        bare.append(time.perf_counter() - started)
    total_steps = len(models) * nstep
    wrapped_rate, bare_rate = total_steps / min(wrapped), total_steps / min(bare)
    print(
        f"{name}: {len(params)} parameter sets x {len(poses0)} trajectories x {nstep} steps, {simulator.nthread} "
        "threads\n"
        f"  MujocoRollouts.simulate  {wrapped_rate:12,.0f} steps/s  ({min(wrapped):.3f} s)\n"
        f"  mujoco.rollout.rollout   {bare_rate:12,.0f} steps/s  ({min(bare):.3f} s)\n"
        f"  ratio {wrapped_rate / bare_rate:.2f} (goal >= 0.8); unstable items "
        f"{int(result.unstable.sum())}/{result.unstable.size}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--dataset", default=str(CUBE_DATA), help="recordings folder with a train split")
    parser.add_argument("--trajectories", type=int, default=275, help="initial states per parameter set")
    parser.add_argument("--parameter-sets", type=int, default=8)
    parser.add_argument("--steps", type=int, default=140, help="frames per rollout")
    parser.add_argument("--substeps", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None, help="default: every core this process may use")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    dataset = read_recordings(args.dataset, splits=["train"])
    poses0, velocities0 = first_frames(dataset)
    picks = rng.integers(0, len(poses0), size=args.trajectories)
    measure(
        f"{dataset.name} ({dataset.n_bodies} bodies)",
        MujocoRollouts(dataset, args.threads, args.substeps),
        parameter_sets(rng, args.parameter_sets, dataset.n_bodies),
        poses0[picks],
        velocities0[picks],
        args.steps,
        args.repeats,
    )
    scene, poses0, velocities0 = three_body_scene(dataset, rng, args.trajectories)
    measure(
        f"{dataset.name}: its first body thrice",
        MujocoRollouts(scene, args.threads, args.substeps),
        parameter_sets(rng, args.parameter_sets, 3),
        poses0,
        velocities0,
        args.steps,
        args.repeats,
    )


if __name__ == "__main__":
    main()
