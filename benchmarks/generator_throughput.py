"""Generator throughput: generate_dataset against bare PyBullet loops over the same scenes, with a cost breakdown."""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import pybullet

from contactbench.generation.bullet import BulletScene
from contactbench.generation.generator import (
    SPLIT_SIZES,
    derive_seed,
    generate_dataset,
    toss_chunks,
    toss_rng,
    worker_context,
)
from contactbench.generation.scenes import SceneSpec, sample_initial_state
from contactbench.generation.solids import solid
from contactbench.meshes import Mesh
from contactbench.recordings import read_recordings, write_recordings
from contactbench.sim.bullet_world import BulletSettings

SETTINGS = BulletSettings()
CUBE_SPEC = SceneSpec("frictioncubes", friction=0.5, restitution=0.0)
MULTICUBES_SPEC = SceneSpec("multicubes", friction=0.18, restitution=0.125, bodies=5, center_bias_speed=0.5)
# The 22 variants of Table 1 by body count: frictioncubes 5 + bouncycubes 5 + polyhedra 7 single-body variants,
# and multicubes with 1..5 bodies.
SINGLE_BODY_VARIANTS = 17
MULTICUBES_BODY_COUNTS = (1, 2, 3, 4, 5)

State = tuple[np.ndarray, np.ndarray]

# ---------------------------------------------------------------- the two reference loops


def step_only(scene: BulletScene, states: list[State]) -> None:
    """The bare loop of the goal: every toss stepped as the generator steps it, nothing read back."""
    client, step = scene.client, pybullet.stepSimulation
    for poses, velocities in states:
        scene.set_state(poses, velocities)
        for _ in range(SETTINGS.frames - 1):
            step(client)


def step_and_read(scene: BulletScene, states: list[State]) -> None:
    """The cheapest loop that gets a recording out of PyBullet's Python API: the generator's stepping plus its two
    state reads per body and frame (pose, velocity), kept as PyBullet returns them and never converted."""
    client, bodies, step = scene.client, scene.bodies, pybullet.stepSimulation
    read_pose, read_velocity = pybullet.getBasePositionAndOrientation, pybullet.getBaseVelocity
    for poses, velocities in states:
        scene.set_state(poses, velocities)
        readings = []
        record = readings.append
        for frame in range(SETTINGS.frames):
            if frame:
                step(client)
            for body in bodies:
                record(read_pose(body, client))
                record(read_velocity(body, client))


Loop = Callable[[BulletScene, list[State]], None]

_worker_scene: BulletScene | None = None  # each pool process's own scene, as the generator's workers hold one


def _open_worker_scene(mesh: Mesh, spec: SceneSpec) -> None:
    global _worker_scene
    _worker_scene = BulletScene(mesh, spec, SETTINGS)


def _run_in_worker(loop: Loop, states: list[State]) -> None:
    loop(_worker_scene, states)


def initial_states(spec: SceneSpec, tosses: int, seed: int) -> list[State]:
    """The generator's own initial states for tosses 0..tosses-1."""
    mesh = solid(spec.faces)
    derived = derive_seed(seed, spec)
    return [sample_initial_state(spec, mesh, toss_rng(derived, toss)) for toss in range(tosses)]


def pool_seconds(loop: Loop, spec: SceneSpec, states: list[State], workers: int) -> float:
    """Wall time of `loop` over `states` laid out as generate_dataset lays out its tosses: a fresh pool of as many
    processes from the same start method, one scene each made when the process starts, the same chunks handed
    out in the same order. The states are drawn beforehand, outside the timing: drawing them is generator work."""
    chunks = [states[chunk.start : chunk.stop] for chunk in toss_chunks(len(states), workers)]
    mesh = solid(spec.faces)  # made once and shipped to the workers, as generate_dataset does
    start = time.perf_counter()
    if workers == 1:
        with BulletScene(mesh, spec, SETTINGS) as scene:
            for chunk in chunks:
                loop(scene, chunk)
    else:
        with ProcessPoolExecutor(
            workers, mp_context=worker_context(), initializer=_open_worker_scene, initargs=(mesh, spec)
        ) as pool:
            for future in as_completed([pool.submit(_run_in_worker, loop, chunk) for chunk in chunks]):
                future.result()
    return time.perf_counter() - start


# ---------------------------------------------------------------- measurements


def _split_sizes(tosses: int) -> dict[str, int]:
    """The paper's 275/165/110 proportions for `tosses` tosses in all."""
    if tosses == sum(SPLIT_SIZES.values()):
        return dict(SPLIT_SIZES)
    train = max(1, tosses // 2)
    val = max(1, (tosses - train) * 3 // 5)
    return {"train": train, "val": val, "test": max(1, tosses - train - val)}


def _generate(spec: SceneSpec, tosses: int, workers: int, seed: int, folder: Path) -> Path:
    return generate_dataset(
        spec, folder / spec.name, split_sizes=_split_sizes(tosses), seed=seed, workers=workers, progress=False
    )


def parallel_seconds(
    spec: SceneSpec, tosses: int, workers: int, seed: int, folder: Path, repeat: int
) -> dict[str, float]:
    """Wall seconds of generate_dataset and of the two reference loops, one run each, in an order that rotates
    with `repeat` so that a change in the machine's load does not always fall on the same one."""
    states = initial_states(spec, tosses, seed)
    runs = {
        "generator": lambda: _timed(lambda: _generate(spec, tosses, workers, seed, folder)),
        "stepping": lambda: pool_seconds(step_only, spec, states, workers),
        "stepping + reads": lambda: pool_seconds(step_and_read, spec, states, workers),
    }
    names = list(runs)
    order = names[repeat % len(names) :] + names[: repeat % len(names)]
    return {name: runs[name]() for name in order}


def in_process_milliseconds(spec: SceneSpec, tosses: int, seed: int) -> dict[str, float]:
    """CPU milliseconds per toss in this one process and one scene (CPU time barely moves with other processes'
    load), each line adding one part of a generator worker's work to the line before it."""
    mesh = solid(spec.faces)
    derived = derive_seed(seed, spec)
    states = initial_states(spec, tosses, seed)
    with BulletScene(mesh, spec, SETTINGS) as scene:
        runs = {
            "stepping": lambda: step_only(scene, states),
            "stepping + reads": lambda: step_and_read(scene, states),
            "BulletScene.simulate": lambda: [
                scene.simulate(poses, velocities, SETTINGS.frames) for poses, velocities in states
            ],
            "+ sampling the state": lambda: [
                scene.simulate(*sample_initial_state(spec, mesh, toss_rng(derived, toss)), SETTINGS.frames)
                for toss in range(tosses)
            ],
        }
        return {name: 1e3 * _cpu_timed(run) / tosses for name, run in runs.items()}


def writing_seconds(dataset: Path, folder: Path) -> float:
    """Time write_recordings alone takes for a generated dataset (it runs after the workers are done)."""
    recordings = read_recordings(dataset)
    return _timed(lambda: write_recordings(folder / "rewritten", recordings))


def _timed(run: Callable[[], object]) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def _cpu_timed(run: Callable[[], object]) -> float:
    start = time.process_time()
    run()
    return time.process_time() - start


def _medians(rows: list[dict[str, float]]) -> dict[str, float]:
    return {name: statistics.median(row[name] for row in rows) for name in rows[0]}


def report(
    spec: SceneSpec, tosses: int, parallel: list[dict[str, float]], in_process: list[dict[str, float]], writing: float
) -> None:
    seconds = _medians(parallel)
    # Each run's ratio against the reference loop run right beside it, then the median over the repeats.
    goal = [row["stepping"] / row["generator"] for row in parallel]
    ceiling = [row["stepping"] / row["stepping + reads"] for row in parallel]
    overhead = [row["stepping + reads"] / row["generator"] for row in parallel]
    print(f"  {spec.name} bodies={spec.bodies}, {len(parallel)} runs, medians:")
    for name, value in seconds.items():
        print(f"    {name:<18} {value:6.2f} s = {tosses / value:5.0f} tosses/s")
    print(
        f"    ratio generator / bare stepping loop: {statistics.median(goal):.2f} "
        f"(runs {min(goal):.2f}..{max(goal):.2f}; goal >= 0.8)\n"
        f"    ratio stepping + reads / bare stepping loop: {statistics.median(ceiling):.2f} "
        f"(the most any recorder using PyBullet's Python API can reach)\n"
        f"    ratio generator / stepping + reads: {statistics.median(overhead):.2f} (the generator's own cost)\n"
        f"    of the generator, writing the dataset (write_recordings alone, after the workers): {writing:.2f} s"
    )
    milliseconds = _medians(in_process)
    stepping = milliseconds["stepping"]
    print("    in one process, CPU ms per toss (extra = over the line above; % of stepping):")
    previous = 0.0
    for name, value in milliseconds.items():
        extra = f"  extra {value - previous:5.2f} ms = {100 * (value - previous) / stepping:3.0f}%" if previous else ""
        print(f"      {name:<20} {value:5.2f} ms  ratio {stepping / value:.2f}{extra}")
        previous = value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--tosses",
        type=int,
        default=sum(SPLIT_SIZES.values()),
        help="tosses per measured variant (default: a whole variant)",
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=5, help="runs of everything, interleaved; medians are reported")
    args = parser.parse_args()

    print(
        f"pybullet generator, {args.tosses} tosses per variant, {args.workers} workers, {args.repeats} runs "
        f"(cores may be shared: medians of interleaved runs)\n"
        f"  generator: generate_dataset, sampling, simulating, recording and writing\n"
        f"  stepping: the same tosses only stepped; stepping + reads: also the two PyBullet state reads per body and "
        f"frame a recording needs, results kept unconverted; both in the generator's pool layout"
    )
    in_process_tosses = min(args.tosses, 100)
    with tempfile.TemporaryDirectory() as folder:
        # Start the worker machinery once, as a run over many variants would: the first pool pays it alone.
        warm_up = _timed(
            lambda: generate_dataset(
                CUBE_SPEC, Path(folder) / "warm_up", split_sizes=_split_sizes(3), workers=args.workers, progress=False
            )
        )
        print(f"  worker start-up, first variant of a run only: {warm_up:.2f} s")
        generator_seconds = {}
        for spec in (CUBE_SPEC, MULTICUBES_SPEC):
            parallel, in_process = [], []
            for repeat in range(args.repeats):
                parallel.append(parallel_seconds(spec, args.tosses, args.workers, args.seed, Path(folder), repeat))
                in_process.append(in_process_milliseconds(spec, in_process_tosses, args.seed))
            writing = writing_seconds(_generate(spec, args.tosses, args.workers, args.seed, Path(folder)), Path(folder))
            report(spec, args.tosses, parallel, in_process, writing)
            generator_seconds[spec.bodies] = _medians(parallel)["generator"]
    # Cost grows about linearly with the body count between the two measured ends; other solids cost about
    # what a cube costs.
    per_body = (generator_seconds[5] - generator_seconds[1]) / 4
    multicubes = sum(generator_seconds[1] + per_body * (bodies - 1) for bodies in MULTICUBES_BODY_COUNTS)
    estimate = (SINGLE_BODY_VARIANTS * generator_seconds[1] + multicubes) * sum(SPLIT_SIZES.values()) / args.tosses
    print(
        f"  estimate for all 22 variants of {sum(SPLIT_SIZES.values())} tosses: {estimate:.0f} s "
        f"({estimate / 60:.1f} min)"
    )


if __name__ == "__main__":
    main()
