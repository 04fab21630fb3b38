"""Times compute_metrics on 110 tosses x 140 frames x 3 cubes, and eq. (1) on a SysID-sized candidate batch."""

from __future__ import annotations

import argparse
import time

import numpy as np

from contactbench import rotations
from contactbench.generation.solids import WIDTH, solid
from contactbench.metrics import compute_metrics, configuration_error


def clustered_cubes(rng: np.random.Generator, n_trajectories: int, n_frames: int, n_bodies: int) -> np.ndarray:
    """Cubes tumbling on random walks within about a width of each other, so most pairs reach the full SAT test."""
    steps = rng.normal(scale=0.1 * WIDTH, size=(n_trajectories, n_frames, n_bodies, 3))
    start = rng.normal(scale=WIDTH, size=(n_trajectories, 1, n_bodies, 3))
    positions = start + np.cumsum(steps, axis=1) / np.sqrt(np.arange(1, n_frames + 1))[:, None, None]
    positions[..., 2] = np.abs(positions[..., 2]) + WIDTH / 2
    # Accumulated rotation vectors are not composed rotations, but they tumble smoothly, which is all timing needs.
    tumbling = rotations.from_rotation_vector(
        np.cumsum(rng.normal(scale=0.1, size=(n_trajectories, n_frames, n_bodies, 3)), axis=1)
    )
    initial = rotations.uniform_random(rng, n_trajectories * n_bodies).reshape(n_trajectories, 1, n_bodies, 4)
    orientations = rotations.multiply(tumbling, initial)
    return np.concatenate([positions, orientations], axis=-1)


def best_time(function, repeats: int) -> float:
    timings = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        timings.append(time.perf_counter() - started)
    return min(timings)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--trajectories", type=int, default=110)
    parser.add_argument("--frames", type=int, default=140)
    parser.add_argument("--bodies", type=int, default=3)
    parser.add_argument("--start-frame", type=int, default=5)
    parser.add_argument("--candidates", type=int, default=64, help="SysID candidates per configuration_error call")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    true = clustered_cubes(rng, args.trajectories, args.frames, args.bodies)
    pred = clustered_cubes(rng, args.trajectories, args.frames, args.bodies)
    lengths = np.full(args.trajectories, args.frames)
    meshes = [solid(6)] * args.bodies

    result = compute_metrics(true, pred, lengths, args.start_frame, meshes, floor_z=0.0)
    seconds = best_time(
        lambda: compute_metrics(true, pred, lengths, args.start_frame, meshes, floor_z=0.0), args.repeats
    )
    frames = result.summary["scored_frames"]
    print(
        f"compute_metrics: {args.trajectories} x {args.frames} frames x {args.bodies} cubes, {frames} scored frames: "
        f"{seconds * 1e3:.1f} ms, {frames / seconds:,.0f} frames/s "
        f"(pairwise collisions: true {result.summary['pairwise_collisions_true']:.2f}, pred "
        f"{result.summary['pairwise_collisions']:.2f})"
    )

    widths = np.array([mesh.width for mesh in meshes])
    candidates = true[None] + rng.normal(scale=1e-3, size=(args.candidates,) + true.shape)
    seconds = best_time(lambda: configuration_error(true, candidates, widths), args.repeats)
    frames = args.candidates * args.trajectories * args.frames
    print(
        f"configuration_error: {args.candidates} candidates x {args.trajectories} x {args.frames} frames: "
        f"{seconds * 1e3:.1f} ms, {frames / seconds:,.0f} frames/s"
    )


if __name__ == "__main__":
    main()
