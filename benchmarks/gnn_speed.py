"""Mesh GNN throughput on CPU (or GPU): training samples/s and rollout frames/s, for one cube and for three cubes.

Each training rate is printed beside the bare network's (forward + backward of EncodeProcessDecode on the same
graphs, features built once), so the ratio shows what features, edges, the rigid fit and the loss cost on top; and a
training step's FLOPs (torch's FlopCounterMode) against the device's measured matmul throughput at the network's own
shapes (an [edges, latent] x [latent, latent] product), so the distance to the limit is a ratio too.

The single-cube scene is the shipped real cube data. The three-cube scene replays three real tosses side by side,
1.2 widths apart along x, so bodies pass within the collision radius and the graph has the size and the collision
edges of a 3-body scene; it is for timing only (the motion is not physical where the cubes overlap).
    python benchmarks/gnn_speed.py                       # paper network (latent 128, 10 steps), batch 64
    python benchmarks/gnn_speed.py --latent-size 64 --message-passing-steps 5 --threads 1
    python benchmarks/gnn_speed.py --rigid --latent-size 64 --message-passing-steps 5 --batch-size 128 --threads 1

Timed under the CPU kernels training uses (contactbench/models/gnn/cpu_kernels.py). --compare-kernels times the
training step under each named mode instead, each in its own process (torch fixes its kernels once per process),
the modes alternated --repeats times, and prints each mode's median step time and its ratio to the first mode's:
    python benchmarks/gnn_speed.py --rigid --latent-size 48 --message-passing-steps 3 --batch-size 128 --threads 1 \
        --compare-kernels native avx2 compatible
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import subprocess
import sys
import time

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from contactbench.config import REPO_ROOT
from contactbench.models.gnn import cpu_kernels
from contactbench.models.gnn.graph import build_edges
from contactbench.models.gnn.module import GNNDataModule, GNNModule
from contactbench.protocol import Context
from contactbench.recordings import read_recordings
from contactbench.scene import Recordings, Split

SIDE_BY_SIDE_SPACING = 1.2  # widths between neighbouring cubes' origins


def side_by_side(recordings: Recordings, n_bodies: int) -> Recordings:
    """Tosses n, n + 1, ... of each split replayed together, body k shifted k * spacing widths along x."""
    shift = SIDE_BY_SIDE_SPACING * recordings.widths()[0]
    splits = {}
    for name, split in recordings.splits.items():
        count = split.n_trajectories - n_bodies + 1
        poses = np.concatenate(
            [split.poses[k : k + count] + np.array([k * shift, 0, 0, 0, 0, 0, 0]) for k in range(n_bodies)], axis=2
        )
        lengths = np.min([split.lengths[k : k + count] for k in range(n_bodies)], axis=0)
        poses[np.arange(split.n_frames)[None, :] >= lengths[:, None]] = np.nan
        splits[name] = Split(poses, lengths)
    meta = dict(recordings.meta, bodies=[dict(recordings.meta["bodies"][0], name=f"cube_{k}") for k in range(n_bodies)])
    return dataclasses.replace(recordings, meta=meta, splits=splits)


def training_samples_per_second(
    module: GNNModule, dataset: Recordings, batch_size: int, steps: int
) -> tuple[float, float]:
    """Samples/s of whole training steps, and of the bare network's forward + backward on the same graphs."""
    rigid = module.hparams.rigid
    loader = iter(
        GNNDataModule(
            dataset, batch_size=batch_size, velocity_history=module.hparams.velocity_history, rigid=rigid
        ).train_dataloader()
    )
    optimizer = module.optimizer()  # the one training uses

    def step():
        batch = next(loader).to(module.device)
        optimizer.zero_grad()
        module.simulator.loss(batch, add_noise=True).backward()
        optimizer.step()

    simulator = module.simulator
    batch = next(loader).to(module.device)[:, :-1]
    if rigid:
        vertices = simulator.bodies.vertices(batch.double())
        nodes = simulator.node_features_double(vertices)
        current = vertices[:, -1].float()
    else:
        nodes, current = simulator.node_features(batch), batch[:, -1]
    edge_index, n_mesh_edges = build_edges(current, simulator.node_body, simulator.mesh_edges, simulator.radius)
    edges = simulator.edge_features(current, edge_index, n_mesh_edges)

    def bare():
        optimizer.zero_grad()
        simulator.network(nodes, edge_index, edges).square().mean().backward()
        optimizer.step()

    return timed(step, steps, batch_size, module.device), timed(bare, steps, batch_size, module.device)


def step_flops(module: GNNModule, dataset: Recordings, batch_size: int) -> float:
    """Floating-point operations of one training step's forward and backward pass (matmuls; the rest is minor)."""
    rigid = module.hparams.rigid
    loader = GNNDataModule(
        dataset, batch_size=batch_size, velocity_history=module.hparams.velocity_history, rigid=rigid
    )
    batch = next(iter(loader.train_dataloader())).to(module.device)
    with FlopCounterMode(display=False) as counter:
        module.simulator.loss(batch, add_noise=True).backward()
    return float(counter.get_total_flops())


def matmul_flops_per_second(rows: int, latent: int, device: torch.device, repeats: int = 50) -> float:
    """The device's throughput on the network's typical product, [rows, latent] x [latent, latent]."""
    left, right = torch.randn(rows, latent, device=device), torch.randn(latent, latent, device=device)
    for _ in range(3):
        left @ right
    synchronize(device)
    started = time.perf_counter()
    for _ in range(repeats):
        left @ right
    synchronize(device)
    return 2 * rows * latent * latent * repeats / (time.perf_counter() - started)


def timed(step, steps: int, batch_size: int, device: torch.device) -> float:
    step()  # warm-up: allocations, first-call dispatch
    synchronize(device)
    started = time.perf_counter()
    for _ in range(steps):
        step()
    synchronize(device)
    return steps * batch_size / (time.perf_counter() - started)


def rollout_frames_per_second(module: GNNModule, dataset: Recordings, trajectories: int, frames: int) -> float:
    """Predicted frames per second over all trajectories, rolled out together in one batch."""
    split = dataset.split("val").select(range(trajectories))
    context_frames = module.hparams.context_frames
    context = Context(
        poses=split.poses[:, :context_frames],
        velocities=np.zeros(split.poses[:, :context_frames].shape[:-1] + (6,)),
        lengths=np.full(trajectories, context_frames + frames),
    )
    model = module.to_contact_model()
    started = time.perf_counter()
    model.rollout(dataset, context)
    synchronize(module.device)
    return trajectories * frames / (time.perf_counter() - started)


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def compare_kernels(modes: list[str], repeats: int, argv: list[str]) -> None:
    """Training-step time of the first scene under each kernel mode, each run in a fresh process, the modes
    alternated so that a load on shared cores falls on all of them alike."""
    seconds: dict[str, list[float]] = {mode: [] for mode in modes}
    for _ in range(repeats):
        for mode in modes:
            env = {key: value for key, value in os.environ.items() if key not in ("ATEN_CPU_CAPABILITY", "MKL_CBWR")}
            env[cpu_kernels.MODE_VARIABLE] = mode
            done = subprocess.run(
                [sys.executable, __file__, *argv, "--training-only"], env=env, capture_output=True, text=True
            )
            if done.returncode != 0:
                raise SystemExit(f"{mode}: {done.stderr.strip().splitlines()[-1] if done.stderr.strip() else ''}")
            seconds[mode].append(float(done.stdout.split()[-1]))
    base = statistics.median(seconds[modes[0]])
    for mode in modes:
        median = statistics.median(seconds[mode])
        print(
            f"kernels {mode:10s}: training step {median * 1e3:7.1f} ms (median of {repeats}), "
            f"ratio to {modes[0]} {median / base:.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--dataset", default=str(REPO_ROOT / "assets" / "contactnets_cube"), help="a single-body recordings folder"
    )
    parser.add_argument(
        "--bodies", type=int, nargs="+", default=[1, 3], help="scenes to time: this many copies side by side"
    )
    parser.add_argument("--latent-size", type=int, default=128)
    parser.add_argument("--message-passing-steps", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument(
        "--rigid",
        action="store_true",
        help="model=gnn's rigid simulator (3 velocities of history) instead of the paper's",
    )
    parser.add_argument("--train-steps", type=int, default=10)
    parser.add_argument("--rollout-trajectories", type=int, default=16)
    parser.add_argument("--rollout-frames", type=int, default=50)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument(
        "--compare-kernels",
        nargs="+",
        metavar="MODE",
        choices=list(cpu_kernels.MODES),
        help=f"time training steps under each of these CPU kernel modes ({', '.join(cpu_kernels.MODES)})",
    )
    parser.add_argument("--repeats", type=int, default=3, help="with --compare-kernels: processes per mode")
    parser.add_argument("--training-only", action="store_true", help=argparse.SUPPRESS)  # one mode's process
    args = parser.parse_args()
    if args.compare_kernels:
        argv = [arg for arg in sys.argv[1:] if arg not in args.compare_kernels and arg != "--compare-kernels"]
        compare_kernels(args.compare_kernels, args.repeats, argv)
        return
    kernels = cpu_kernels.pin()  # before the first tensor: torch fixes its kernels there
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    single = read_recordings(args.dataset, splits=["train", "val"])

    def built(dataset):
        """The GNN as the command line sets it, on the dataset's scene, ready to train."""
        module = GNNModule(
            dataset,
            latent_size=args.latent_size,
            message_passing_steps=args.message_passing_steps,
            rigid=args.rigid,
            velocity_history=3 if args.rigid else 5,
        ).to(args.device)
        module.setup("fit")
        return module

    if args.training_only:
        module = built(single)
        samples, _ = training_samples_per_second(module, single, args.batch_size, args.train_steps)
        print(args.batch_size / samples)  # seconds per training step
        return
    print(
        f"kernels {kernels['mode']} (ATen {kernels['aten']}, MKL branch {kernels['mkl_cbwr']}), "
        f"device {args.device}, {torch.get_num_threads()} threads, latent {args.latent_size}, "
        f"{args.message_passing_steps} message-passing steps, batch {args.batch_size}, "
        f"{'rigid (gnn)' if args.rigid else 'paper (gnn_paper)'}"
    )
    for n_bodies in args.bodies:
        dataset = single if n_bodies == 1 else side_by_side(single, n_bodies)
        module = built(dataset)
        samples, bare = training_samples_per_second(module, dataset, args.batch_size, args.train_steps)
        frames = rollout_frames_per_second(module, dataset, args.rollout_trajectories, args.rollout_frames)
        flops = step_flops(module, dataset, args.batch_size)
        achieved = flops * samples / args.batch_size
        limit = matmul_flops_per_second(
            args.batch_size * module.simulator.scene.n_nodes * 4, args.latent_size, module.device
        )
        print(
            f"{n_bodies} cube(s), {module.simulator.scene.n_nodes} nodes: training {samples:8.1f} samples/s "
            f"(bare network {bare:8.1f}/s, ratio {samples / bare:.2f}), "
            f"rollout {frames:8.1f} frames/s ({args.rollout_trajectories} trajectories batched)\n"
            f"  a training step: {flops / 1e9:.2f} GFLOP, {achieved / 1e9:.1f} GFLOP/s achieved; matmul at the "
            f"network's shape {limit / 1e9:.1f} GFLOP/s: {achieved / limit:.2f} of the limit"
        )
        if args.rigid and n_bodies > 1:  # the same network, bodies pushed apart after every step (model=gnn's default)
            separating = GNNModule(
                dataset,
                latent_size=args.latent_size,
                message_passing_steps=args.message_passing_steps,
                rigid=True,
                velocity_history=3,
                separate_bodies=True,
            ).to(args.device)
            separating.load_state_dict(module.state_dict())
            separated = rollout_frames_per_second(separating, dataset, args.rollout_trajectories, args.rollout_frames)
            print(f"  with body separation: rollout {separated:8.1f} frames/s (ratio {separated / frames:.2f})")


if __name__ == "__main__":
    main()
