"""Generator throughput: full generate_dataset against a bare PyBullet stepping loop, and whole-variant timings."""
from __future__ import annotations

import argparse
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pybullet

from contactbench.generation.bullet import BulletScene
from contactbench.generation.generator import SPLIT_SIZES, derive_seed, generate_dataset, toss_rng, worker_context
from contactbench.generation.scenes import BulletSettings, SceneSpec, sample_initial_state
from contactbench.generation.solids import solid
from contactbench.recordings import read_recordings, write_recordings

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
    if workers == 1:
        _bare_tosses(spec, states)  # generate_dataset runs in-process too
    else:
        with ProcessPoolExecutor(workers, mp_context=worker_context()) as pool:
            list(pool.map(_bare_tosses, [spec] * workers, shares))
    return time.perf_counter() - start


def generator_seconds(spec: SceneSpec, tosses: int, workers: int, seed: int, folder: Path) -> float:
    start = time.perf_counter()
    generate_dataset(spec, folder / spec.name, split_sizes=_split_sizes(tosses), seed=seed, workers=workers, progress=False)
    return time.perf_counter() - start


def writing_seconds(dataset: Path, folder: Path) -> float:
    """Time write_recordings alone takes for a generated dataset (the part of the generator that is not PyBullet)."""
    recordings = read_recordings(dataset)
    start = time.perf_counter()
    write_recordings(folder / "rewritten", recordings)
    return time.perf_counter() - start


def _split_sizes(tosses: int) -> dict[str, int]:
    """The paper's 275/165/110 proportions for `tosses` tosses in all."""
    if tosses == sum(SPLIT_SIZES.values()):
        return dict(SPLIT_SIZES)
    train = max(1, tosses // 2)
    val = max(1, (tosses - train) * 3 // 5)
    return {"train": train, "val": val, "test": max(1, tosses - train - val)}


def in_process_milliseconds(spec: SceneSpec, tosses: int, seed: int) -> tuple[float, float]:
    """Per-toss cost in one client: BulletScene.simulate (stepping and recording) against stepping alone."""
    mesh = solid(spec.faces)
    derived = derive_seed(seed, spec)
    states = [sample_initial_state(spec, mesh, toss_rng(derived, toss)) for toss in range(tosses)]
    with BulletScene(mesh, spec, SETTINGS) as scene:
        start = time.perf_counter()
        for poses, velocities in states:
            scene.simulate(poses, velocities, SETTINGS.frames)
        recorded = time.perf_counter() - start
    start = time.perf_counter()
    _bare_tosses(spec, states)
    bare = time.perf_counter() - start
    return 1e3 * recorded / tosses, 1e3 * bare / tosses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tosses", type=int, default=sum(SPLIT_SIZES.values()), help="tosses per measured variant (default: a whole variant)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    print(f"pybullet generator, {args.tosses} tosses per variant, {args.workers} workers (cores may be shared: times are noisy)")
    with tempfile.TemporaryDirectory() as folder:
        # Start the worker machinery once, as a run over many variants would: the first pool pays it alone.
        warm_up = time.perf_counter()
        generate_dataset(CUBE_SPEC, Path(folder) / "warm_up", split_sizes=_split_sizes(3), workers=args.workers, progress=False)
        print(f"  worker start-up, first variant of a run only: {time.perf_counter() - warm_up:.2f} s")
        seconds = {}
        for spec in (CUBE_SPEC, MULTICUBES_SPEC):
            generated = generator_seconds(spec, args.tosses, args.workers, args.seed, Path(folder))
            bare = bare_seconds(spec, args.tosses, args.workers, args.seed)
            recorded_ms, bare_ms = in_process_milliseconds(spec, min(args.tosses, 100), args.seed)
            writing = writing_seconds(Path(folder) / spec.name, Path(folder))
            seconds[spec.bodies] = generated
            print(
                f"  {spec.name} bodies={spec.bodies}: generate_dataset {generated:.2f} s = {args.tosses / generated:.0f} tosses/s; "
                f"bare loop {bare:.2f} s = {args.tosses / bare:.0f} tosses/s; ratio {bare / generated:.2f} (goal >= 0.8)\n"
                f"    of which writing the dataset (write_recordings alone): {writing:.2f} s\n"
                f"    in one process per toss: simulate {recorded_ms:.2f} ms, stepping alone {bare_ms:.2f} ms "
                f"(ratio {bare_ms / recorded_ms:.2f})"
            )
    # Cost grows about linearly with the body count between the two measured ends; other solids cost about
    # what a cube costs.
    per_body = (seconds[5] - seconds[1]) / 4
    multicubes = sum(seconds[1] + per_body * (bodies - 1) for bodies in MULTICUBES_BODY_COUNTS)
    estimate = (SINGLE_BODY_VARIANTS * seconds[1] + multicubes) * sum(SPLIT_SIZES.values()) / args.tosses
    print(f"  estimate for all 22 variants of {sum(SPLIT_SIZES.values())} tosses: {estimate:.0f} s ({estimate / 60:.1f} min)")


if __name__ == "__main__":
    main()
