"""SysID objective throughput (evaluations/s) against bare mujoco.rollout on the same work, and the paper-budget
time.

Each generation is timed as the search runs it, then rolled out bare right after it. Bare rolls every asked candidate
out on the generation's tosses to the batch's horizon in one mujoco.rollout call; the objective stops each group of
alike lengths at its last scored frame, so it steps MuJoCo less than bare does. The search's time includes NGOpt's ask
and tell; the objective's line leaves them out.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mujoco.rollout
import nevergrad as ng
import numpy as np

from contactbench.models.sysid.module import stop_recast_threads
from contactbench.models.sysid.objective import ConfigurationObjective, subset
from contactbench.models.sysid.search_space import SearchSpace
from contactbench.recordings import read_recordings
from contactbench.sim.rollout import MujocoRollouts, counted_warnings

CUBE_DATA = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--dataset", type=Path, default=CUBE_DATA)
    parser.add_argument("--generations", type=int, default=30)
    parser.add_argument("--num-workers", type=int, default=16, help="candidates per generation")
    parser.add_argument(
        "--batch-trajectories",
        type=int,
        default=0,
        help="train tosses per evaluation (0: all, as budget=quick and paper)",
    )
    parser.add_argument(
        "--budget", type=int, default=10_000, help="evaluations NGOpt is told it has (picks its algorithm)"
    )
    parser.add_argument("--context-frames", type=int, default=6)
    args = parser.parse_args()

    dataset = read_recordings(args.dataset, ["train"])
    space = SearchSpace(dataset.n_bodies)
    rollouts = MujocoRollouts(dataset)
    objective = ConfigurationObjective(dataset, "train", args.context_frames, rollouts)
    optimizer = ng.optimizers.NGOpt(
        parametrization=space.parametrization(0), budget=args.budget, num_workers=args.num_workers
    )
    rng = np.random.default_rng(0)
    batch = args.batch_trajectories or objective.n_trajectories
    batches = [np.sort(rng.choice(objective.n_trajectories, batch, replace=False)) for _ in range(args.generations)]

    # Each generation as SysID runs it (ask, one batched rollout + equation (1), tell), then the same rollouts bare
    # (prebuilt models, one mujoco.rollout call, nothing else) right after it, so that both see the same machine load.
    steps, search_seconds, objective_seconds, bare_seconds = 0, 0.0, 0.0, 0.0
    for indices in batches:
        started = time.perf_counter()
        candidates = [optimizer.ask() for _ in range(args.num_workers)]
        parameters = [space.to_parameters(c.value) for c in candidates]
        evaluating = time.perf_counter()
        losses = objective(parameters, indices).losses
        objective_seconds += time.perf_counter() - evaluating
        for candidate, loss in zip(candidates, losses):
            optimizer.tell(candidate, float(loss))
        search_seconds += time.perf_counter() - started

        context = subset(objective.context, indices)
        initial = rollouts.initial_states(context.poses[:, -1], context.velocities[:, -1])
        initial = np.tile(initial, (len(parameters), 1))
        models = [rollouts.model(p) for p in parameters for _ in indices]
        n_steps = context.horizon - args.context_frames
        started = time.perf_counter()
        with counted_warnings():  # as simulate does
            mujoco.rollout.rollout(models, rollouts._data, initial, nstep=n_steps, persistent_pool=True)
        bare_seconds += time.perf_counter() - started
        steps += len(models) * n_steps
    stop_recast_threads()

    evaluations = args.generations * args.num_workers
    rate = evaluations / search_seconds
    paper_evaluations = 10_000 * 10  # at this batch size
    print(
        f"scene {dataset.name}: NGOpt -> {type(optimizer.optim).__name__}, {args.generations} generations x "
        f"{args.num_workers} candidates x {batch} trajectories, {rollouts.nthread} threads"
    )
    print(f"search : {rate:8.1f} evaluations/s  {steps / search_seconds:12.0f} steps/s")
    print(
        f"objective: {evaluations / objective_seconds:6.1f} evaluations/s  {steps / objective_seconds:12.0f} steps/s "
        f"(the search less NGOpt's ask and tell, which took {1 - objective_seconds / search_seconds:.0%} of it)"
    )
    print(
        f"bare   : {evaluations / bare_seconds:8.1f} evaluations/s  {steps / bare_seconds:12.0f} steps/s "
        "(mujoco.rollout alone)"
    )
    print(f"ratio search/bare = {bare_seconds / search_seconds:.2f}  (goal >= 0.8)")
    print(f"ratio objective/bare = {bare_seconds / objective_seconds:.2f}")
    print(
        "paper budget (10 restarts x 10,000 evaluations) on this machine: about "
        f"{paper_evaluations / rate / 3600:.1f} h"
    )


if __name__ == "__main__":
    main()
