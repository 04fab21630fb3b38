"""Diagnosis objective throughput: robust short-horizon losses of candidate batches vs bare mujoco.rollout, same
work."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mujoco.rollout
import numpy as np

from contactbench.diagnosis.fitting import ResidualFit
from contactbench.diagnosis.library import Hypothesis, library
from contactbench.diagnosis.segments import SegmentSimulator, cut_segments
from contactbench.recordings import read_recordings
from contactbench.sim.rollout import counted_warnings

CUBE_DATA = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--dataset", type=Path, default=CUBE_DATA)
    parser.add_argument("--trajectories", type=int, default=60, help="train tosses (budget=quick's fit_trajectories)")
    parser.add_argument("--segment-frames", type=int, default=16)
    parser.add_argument("--batch", type=int, default=16, help="candidates per batched call")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    dataset = read_recordings(args.dataset, ["train"]).for_models(["train"])
    train = dataset.split("train")
    segments = cut_segments(
        dataset, train.select(range(min(args.trajectories, train.n_trajectories))), args.segment_frames
    )
    fit = ResidualFit(SegmentSimulator(dataset, segments), scale=0.05)
    # A hypothesis with an effect that changes the compiled model per candidate (the costly case: no cache hits).
    hypothesis = Hypothesis(dataset.n_bodies, (library(float(dataset.widths().max()))["floor_tilt"],))
    lower, upper = hypothesis.bounds()
    rng = np.random.default_rng(0)
    batches = [lower + rng.random((args.batch, len(lower))) * (upper - lower) for _ in range(args.repeats)]

    started = time.perf_counter()
    for batch in batches:
        fit.loss(hypothesis, batch)
    objective_seconds = time.perf_counter() - started

    rollouts = fit.simulator.rollouts
    initial = rollouts.initial_states(segments.poses0, segments.velocities0)
    prepared = [
        [rollouts.model(hypothesis.contact_parameters(v)) for v in batch for _ in range(segments.count)]
        for batch in batches
    ]
    states = np.empty((args.batch * segments.count, args.segment_frames, rollouts.nstate))
    started = time.perf_counter()
    with counted_warnings():  # as the library's rollouts do
        for models in prepared:
            mujoco.rollout.rollout(
                models,
                rollouts._data,
                np.tile(initial, (args.batch, 1)),
                nstep=args.segment_frames,
                state=states,
                persistent_pool=True,
            )
    bare_seconds = time.perf_counter() - started

    steps = args.repeats * args.batch * segments.count * args.segment_frames
    print(
        f"{segments.count} segments x {args.segment_frames} frames, {args.batch} candidates x {args.repeats} batches "
        f"({steps} steps)"
    )
    print(
        f"objective (build models + rollout + residuals + robust loss): {steps / objective_seconds:,.0f} steps/s, "
        f"{args.batch * args.repeats / objective_seconds:.1f} candidates/s"
    )
    print(f"bare mujoco.rollout (models prebuilt): {steps / bare_seconds:,.0f} steps/s")
    print(f"ratio objective / bare = {bare_seconds / objective_seconds:.2f}")


if __name__ == "__main__":
    main()
