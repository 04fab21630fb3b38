"""Generator throughput: full generate_dataset against a bare PyBullet stepping loop, and whole-variant timings."""
from __future__ import annotations

import argparse
import multiprocessing
import tempfile
import time
from pathlib import Path

import numpy as np
import pybullet

from contactbench.generation.bullet import BulletScene
from contactbench.generation.generator import SPLIT_SIZES, derive_seed, generate_dataset, toss_rng
from contactbench.generation.scenes import BulletSettings, SceneSpec, sample_initial_state
from contactbench.generation.solids import solid

SETTINGS = BulletSettings()
CUBE_SPEC = SceneSpec("frictioncubes", friction=0.5, restitution=0.0)
MULTICUBES_SPEC = SceneSpec("multicubes", friction=0.18, restitution=0.125, bodies=5, center_bias_speed=0.5)
# The 22 variants of Table 1 by body count: frictioncubes 5 + bouncycubes 5 + polyhedra 7 single-body variants,
# and multicubes with 1..5 bodies.
SINGLE_BODY_VARIANTS = 17
MULTICUBES_BODY_COUNTS = (1, 2, 3, 4, 5)


def _bare_tosses(spec: SceneSpec, states: list[tuple[np.ndarray, np.ndarray]]) -> int:
    """Step the tosses in one fresh client, as the generator's workers do, but record nothing."""
    with BulletScene(solid(spec.faces), spec, SETTINGS) as scene:
        for poses, velocities in states:
            scene.set_state(poses, velocities)
            for _ in range(SETTINGS.frames - 1):
                pybullet.stepSimulation(scene.client)
    return len(states)


def bare_seconds(spec: SceneSpec, tosses: int, workers: int, seed: int) -> float:
    """Wall time of the bare loop over the generator's own initial states, same process pool layout."""
    mesh = solid(spec.faces)
    derived = derive_seed(seed, spec)
    states = [sample_initial_state(spec, mesh, toss_rng(derived, toss)) for toss in range(tosses)]
    shares = [states[worker::workers] for worker in range(workers)]
    start = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        pool.starmap(_bare_tosses, [(spec, share) for share in shares])
    return time.perf_counter() - start


def generator_seconds(spec: SceneSpec, split_sizes: dict[str, int], workers: int, seed: int, folder: Path) -> float:
    start = time.perf_counter()
    generate_dataset(spec, folder / spec.name, split_sizes=split_sizes, seed=seed, workers=workers, progress=False)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tosses", type=int, default=110, help="tosses in the generator-versus-bare comparison")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-variants", action="store_true", help="skip timing whole 550-toss variants")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as folder:
        print(f"pybullet generator throughput, {args.workers} workers (the cores may be shared: absolute times are noisy)")
        for spec in (CUBE_SPEC, MULTICUBES_SPEC):
            generated = generator_seconds(spec, {"train": args.tosses}, args.workers, args.seed, Path(folder))
            bare = bare_seconds(spec, args.tosses, args.workers, args.seed)
            print(
                f"  {spec.name} bodies={spec.bodies}: generator {args.tosses / generated:7.1f} tosses/s, "
                f"bare loop {args.tosses / bare:7.1f} tosses/s, ratio {bare / generated:.2f} (goal >= 0.8)"
            )
        if args.skip_variants:
            return
        total_tosses = sum(SPLIT_SIZES.values())
        single = generator_seconds(CUBE_SPEC, SPLIT_SIZES, args.workers, args.seed, Path(folder))
        multi = generator_seconds(MULTICUBES_SPEC, SPLIT_SIZES, args.workers, args.seed, Path(folder))
        print(f"  whole variant ({total_tosses} tosses): cube {single:.1f} s, multicubes bodies=5 {multi:.1f} s")
        # Cost grows about linearly with the body count between the two measured ends; other solids cost
        # about what a cube costs.
        per_body = (multi - single) / 4
        multicubes = sum(single + per_body * (bodies - 1) for bodies in MULTICUBES_BODY_COUNTS)
        estimate = SINGLE_BODY_VARIANTS * single + multicubes
        print(f"  estimate for all 22 variants: {estimate:.0f} s ({estimate / 60:.1f} min)")


if __name__ == "__main__":
    main()
