"""What DrakeWorld and SteppedRollouts cost over Drake's bare stepping loop, in the same run, on the real cube.

The bare loop builds the plant once (add_scene, the same contact settings) and per toss sets the state and calls
Simulator.AdvanceTo frame by frame, reading nothing back; the wrapper rolls the same tosses out through
DrakeEngine.rollouts with one and with two worker processes (their start-up included in a first, untimed call).
python benchmarks/drake_rollout.py [--tosses 40] [--frames 140] [--repeats 3]
python benchmarks/drake_rollout.py --segments --frames 16   # the diagnosis' short segments: every 16th frame a start
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from metrics_speed import best_time  # a sibling script: python benchmarks/... puts benchmarks/ on the path
from pydrake.systems.analysis import Simulator

from contactbench.config import REPO_ROOT
from contactbench.recordings import read_recordings
from contactbench.sim.drake_engine import DrakeEngine, new_plant
from contactbench.sim.drake_plant import add_scene
from contactbench.sim.drake_scene import DrakeParameters


def bare_loop(scene, parameters: DrakeParameters, poses0: np.ndarray, velocities0: np.ndarray, frames: int):
    """Drake alone: one diagram, per toss a state and frame-by-frame AdvanceTo."""
    builder, plant, scene_graph = new_plant(scene, 1, "point")
    add_scene(plant, scene_graph, scene, parameters)
    plant.Finalize()
    simulator = Simulator(builder.Build())
    context = simulator.get_mutable_context()
    plant_context = plant.GetMyMutableContextFromRoot(context)
    body = plant.GetBodyByName("body0")
    q, v = body.floating_positions_start(), body.floating_velocities_start_in_v()

    def run() -> None:
        for pose, velocity in zip(poses0[:, 0], velocities0[:, 0]):
            positions, speeds = np.zeros(plant.num_positions()), np.zeros(plant.num_velocities())
            positions[q : q + 7] = np.r_[pose[3:] / np.linalg.norm(pose[3:]), pose[:3]]
            speeds[v : v + 6] = np.r_[velocity[3:], velocity[:3]]
            context.SetTime(0.0)
            plant.SetPositionsAndVelocities(plant_context, np.r_[positions, speeds])
            simulator.Initialize()
            for frame in range(1, frames + 1):
                simulator.AdvanceTo(frame * plant.time_step())

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tosses", type=int, default=40)
    parser.add_argument("--frames", type=int, default=140)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--segments", action="store_true", help="start a toss at every --frames-th recorded frame, not only the first"
    )
    args = parser.parse_args()
    dataset = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["test"])
    split = dataset.split("test")
    count = min(args.tosses, split.n_trajectories)
    starts = np.arange(0, split.n_frames - args.frames, args.frames) if args.segments else np.array([0])
    poses0 = split.poses[:count, starts].reshape(-1, *split.poses.shape[2:])
    velocities0 = split.velocities[:count, starts].reshape(-1, *split.velocities.shape[2:])
    recorded = np.isfinite(poses0).all(axis=(1, 2)) & np.isfinite(velocities0).all(axis=(1, 2))
    poses0, velocities0 = poses0[recorded], velocities0[recorded]
    count = len(poses0)
    engine = DrakeEngine()
    parameters = engine.from_values(
        {"object_friction_0": 0.3, "floor_friction": 0.3, "point_stiffness": 1e4, "hunt_crossley_dissipation": 1.0}, 1
    )
    scene = dataset.for_models()
    bare = best_time(bare_loop(scene, parameters, poses0, velocities0, args.frames), args.repeats)
    print(f"real cube: {count} tosses x {args.frames} frames, dt {dataset.dt * 1e3:.2f} ms; best of {args.repeats}")
    print(f"bare Drake loop:           {bare:.3f} s  {count / bare:7.1f} tosses/s  {bare / count * 1e3:.2f} ms/toss")
    for nthread in (1, 2):
        rollouts = engine.rollouts(scene, nthread=nthread)
        try:
            started = time.perf_counter()
            rollouts.simulate(parameters, poses0, velocities0, args.frames)  # builds the worlds, starts workers
            first = time.perf_counter() - started
            wrapped = best_time(
                lambda rollouts=rollouts: rollouts.simulate(parameters, poses0, velocities0, args.frames), args.repeats
            )
        finally:
            rollouts.close()
        print(
            f"SteppedRollouts nthread={nthread}: {wrapped:.3f} s  {count / wrapped:7.1f} tosses/s  "
            f"{wrapped / count * 1e3:.2f} ms/toss  wrapper/bare {wrapped / bare:.2f}  (first call {first:.2f} s)"
        )


if __name__ == "__main__":
    main()
