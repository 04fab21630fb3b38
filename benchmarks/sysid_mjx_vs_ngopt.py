"""Gradient descent through MJX (model=sysid_mjx) against NGOpt (model=sysid): C-MuJoCo val loss against wall time,
from the same start, in the same run, and the ratio of their times to NGOpt's best val loss.

Both search sysid's Table 2c space from NGOpt's starting point (the domain's centre, damping 50) at budget=quick's
settings: NGOpt asks 16 candidates a generation on 25 random train tosses; Adam steps on 64 random 16-frame train
windows simulated in MJX, gradients by jax.jacfwd. Every few steps each scores its current recommendation on all val
tosses with the C-MuJoCo objective that selects every SysID model. Wall time counts the search alone (val scoring
left out of both); MJX's jit compile is reported apart and added in the second ratio.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import nevergrad as ng
import numpy as np

from contactbench.models.sysid.gradient import MjxWindows, adam_step, decayed
from contactbench.models.sysid.module import stop_recast_threads
from contactbench.models.sysid.objective import ConfigurationObjective
from contactbench.models.sysid.search_space import SearchSpace
from contactbench.recordings import read_recordings
from contactbench.sim.rollout import MujocoRollouts

CUBE_DATA = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"


def ngopt_curve(space, train, val, generations: int, every: int, batch: int, seed: int) -> list[tuple[float, float]]:
    optimizer = ng.optimizers.NGOpt(
        parametrization=space.parametrization(seed), budget=generations * 16, num_workers=16
    )
    rng = np.random.default_rng(seed)
    clock, curve = 0.0, []
    for generation in range(generations + 1):
        if generation % every == 0 or generation == generations:
            recommendation = space.to_parameters(optimizer.provide_recommendation().value)
            curve.append((clock, float(val([recommendation]).losses[0])))
        if generation == generations:
            break
        started = time.perf_counter()
        candidates = [optimizer.ask() for _ in range(16)]
        indices = np.sort(rng.choice(train.n_trajectories, min(batch, train.n_trajectories), replace=False))
        losses = train([space.to_parameters(c.value) for c in candidates], indices).losses
        for candidate, loss in zip(candidates, losses):
            optimizer.tell(candidate, float(loss))
        clock += time.perf_counter() - started
    stop_recast_threads()
    return curve


def mjx_curve(dataset, space, val, steps: int, every: int, windows: int, frames: int, lr: float, seed: int):
    started = time.perf_counter()
    mjx = MjxWindows(dataset, space, 6, frames, position_exponent=2)
    split = dataset.split("train")
    coordinates = mjx.coordinates.start.copy()
    moments = (np.zeros_like(coordinates), np.zeros_like(coordinates))
    mjx.value_and_gradient(coordinates, mjx.windows(split, dataset.dt, windows, np.random.default_rng([seed, steps])))
    compile_seconds = time.perf_counter() - started
    clock, curve = 0.0, []
    for step in range(steps + 1):
        if step % every == 0 or step == steps:
            curve.append((clock, float(val([space.from_vector(mjx.coordinates.to_vector(coordinates))]).losses[0])))
        if step == steps:
            break
        started = time.perf_counter()
        batch = mjx.windows(split, dataset.dt, windows, np.random.default_rng([seed, step]))
        loss, gradient = mjx.value_and_gradient(coordinates, batch)
        if np.isfinite(loss) and np.isfinite(gradient).all():
            coordinates, moments = adam_step(coordinates, moments, gradient, decayed(lr, step, steps), step)
        clock += time.perf_counter() - started
    return curve, compile_seconds, space.describe(space.from_vector(mjx.coordinates.to_vector(coordinates)))


def first_reaching(curve: list[tuple[float, float]], target: float) -> float:
    return next((seconds for seconds, loss in curve if loss <= target), float("nan"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--dataset", type=Path, default=CUBE_DATA)
    parser.add_argument("--generations", type=int, default=50, help="NGOpt generations of 16 (quick: 800 evaluations)")
    parser.add_argument("--steps", type=int, default=150, help="Adam steps (quick)")
    parser.add_argument("--windows", type=int, default=64)
    parser.add_argument("--window-frames", type=int, default=16)
    parser.add_argument("--lr", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    dataset = read_recordings(args.dataset)
    space = SearchSpace(dataset.n_bodies)
    rollouts = MujocoRollouts(dataset)
    train = ConfigurationObjective(dataset, "train", 6, rollouts, position_exponent=2)
    val = ConfigurationObjective(dataset, "val", 6, rollouts, position_exponent=2)
    ngopt = ngopt_curve(space, train, val, args.generations, 5, 25, args.seed)
    gradient, compile_seconds, found = mjx_curve(
        dataset, space, val, args.steps, 10, args.windows, args.window_frames, args.lr, args.seed
    )
    rollouts.close()
    print(f"dataset {args.dataset}: C-MuJoCo val loss (eq. 1, p=2) against search seconds (val scoring left out)")
    for name, curve in (("NGOpt", ngopt), ("MJX + Adam", gradient)):
        print(f"{name:>11}: " + "  ".join(f"{seconds:.1f}s {loss:.4f}" for seconds, loss in curve))
    print(f"MJX compile: {compile_seconds:.1f} s; MJX's last parameters: {found}")
    target = min(loss for _, loss in ngopt)
    ngopt_seconds, mjx_seconds = first_reaching(ngopt, target), first_reaching(gradient, target)
    print(
        f"NGOpt's best val loss {target:.4f}: NGOpt {ngopt_seconds:.1f} s, MJX {mjx_seconds:.1f} s "
        f"(+ {compile_seconds:.1f} s compile)"
    )
    if np.isfinite(mjx_seconds):
        print(
            f"time ratio MJX / NGOpt to that loss: {mjx_seconds / ngopt_seconds:.2f} "
            f"({(mjx_seconds + compile_seconds) / ngopt_seconds:.2f} with compile)"
        )
    else:
        best = min(loss for _, loss in gradient)
        print(
            f"MJX did not reach it in {args.steps} steps: its best val loss {best:.4f} ({best / target:.3f}x NGOpt's)"
        )


if __name__ == "__main__":
    main()
