"""Benchmark dataset generation: seed, sample and simulate every toss of a scene variant, write the recordings."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib.metadata
import json
import multiprocessing
import os
from collections.abc import Mapping
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from contactbench.generation.articulated import Elbow, ElbowScene, sample_elbow_state
from contactbench.generation.bullet import CONTACT_KEYS, BulletScene
from contactbench.generation.effects import NONE, ConcealedEffects
from contactbench.generation.nonconvex import nonconvex_shape
from contactbench.generation.scenes import ELBOW, SceneSpec, SpawnError, sample_initial_state
from contactbench.generation.solids import SOLID_NAMES, solid
from contactbench.generation.terrain import terrain
from contactbench.ground import Ground
from contactbench.meshes import Mesh
from contactbench.processes import standard_start_method
from contactbench.recordings import write_recordings
from contactbench.scene import FORMAT, SCENE_VERSION, VERSION, Recordings, Split, Static, static_entries
from contactbench.sim.bullet_world import BODY_DYNAMICS_OVERRIDES, ENGINE_STATE_SIZE, BulletSettings, recorded_motion

SPLIT_SIZES = {"train": 275, "val": 165, "test": 110}  # tosses per variant (paper, Section 3)
SEEDING = (
    "derived_seed = first 63 bits of sha256(json [seed, name, friction, restitution, faces, bodies]); "
    "toss i (counted across splits in order) draws from numpy default_rng(SeedSequence(derived_seed, spawn_key=(i,)))"
)


def derive_seed(seed: int, spec: SceneSpec) -> int:
    """The variant's own seed: independent across variants, and unchanged by fields that are not its identity (a
    shape or ground joins the identity only when set, so the paper's variants keep their seeds)."""
    identity = [int(seed), spec.name, spec.friction, spec.restitution, spec.faces, spec.bodies]
    identity += [spec.shape] if spec.shape else []
    identity += [spec.ground] if spec.ground != "flat" else []
    identity += [spec.joint_damping] if spec.joint_damping else []
    digest = hashlib.sha256(json.dumps(identity).encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def toss_rng(derived_seed: int, toss: int) -> np.random.Generator:
    """Toss `toss`'s own stream, so a toss does not depend on which worker runs it or what ran before."""
    return np.random.default_rng(np.random.SeedSequence(derived_seed, spawn_key=(toss,)))


@dataclass(frozen=True)
class _Job:
    mesh: Mesh
    pieces: tuple[Mesh, ...]
    static: tuple[tuple[Static, Mesh | None], ...]
    spec: SceneSpec
    settings: BulletSettings
    derived_seed: int
    split_sizes: tuple[tuple[str, int], ...]
    record_contacts: bool
    effects: ConcealedEffects = NONE
    elbow: Elbow | None = None

    def place(self, toss: int) -> str:
        """Where toss `toss` lands, e.g. "val toss 3"."""
        start = 0
        for name, size in self.split_sizes:
            if toss < start + size:
                return f"{name} toss {toss - start}"
            start += size
        raise IndexError(f"toss {toss} is beyond the {start} tosses of the splits")


@dataclass(frozen=True)
class _Chunk:
    """Consecutive tosses from `start`, recorded: poses [n, T, K, 7], velocities [n, T, K, 6], contact arrays."""

    start: int
    poses: np.ndarray
    velocities: np.ndarray
    contacts: dict[str, np.ndarray]


class _TossRunner:
    """Simulates chunks of tosses by index in one PyBullet client (one per process)."""

    def __init__(self, job: _Job):
        self.job = job
        if job.elbow is not None:
            self.scene = ElbowScene(job.elbow, job.spec, job.settings)
        else:
            self.scene = BulletScene(job.mesh, job.spec, job.settings, job.effects, job.pieces, job.static)
        self.ground = Ground.of_static(0.0, [entry for entry, _ in job.static], {e.mesh: m for e, m in job.static})

    def __call__(self, tosses: range) -> _Chunk:
        job, frames, bodies = self.job, self.job.settings.frames, self.job.spec.bodies
        states = np.empty((len(tosses), frames, bodies, ENGINE_STATE_SIZE))
        initial_orientations = np.empty((len(tosses), bodies, 4))
        contacts = (
            {key: np.empty((len(tosses), frames, bodies, 3)) for key in CONTACT_KEYS} if job.record_contacts else {}
        )
        for row, toss in enumerate(tosses):
            try:
                rng = toss_rng(job.derived_seed, toss)
                if job.elbow is not None:
                    poses, velocities = sample_elbow_state(job.spec, job.elbow, rng)
                else:
                    poses, velocities = sample_initial_state(job.spec, job.mesh, rng, self.ground)
            except SpawnError as error:
                raise SpawnError(f"toss {toss} ({job.place(toss)}): {error}") from None
            states[row], wrenches = self.scene.toss(poses, velocities, frames, record_contacts=job.record_contacts)
            initial_orientations[row] = poses[:, 3:]
            for key in contacts:
                contacts[key][row] = wrenches[key]
        # One vectorised conversion per chunk rather than per toss: the numpy calls' overhead is per call.
        poses, velocities = recorded_motion(states, initial_orientations)
        return _Chunk(tosses.start, poses, velocities, contacts)


_worker_runner: _TossRunner | None = None  # each pool process's own runner, set by _start_worker


def _start_worker(job: _Job) -> None:
    global _worker_runner
    _worker_runner = _TossRunner(job)


def _run_in_worker(tosses: range) -> _Chunk:
    return _worker_runner(tosses)


def toss_chunks(total: int, workers: int, largest: int = 32) -> list[range]:
    """Consecutive toss ranges covering 0..total, in order, shrinking toward the end.

    Each is at most `largest` (the progress bar moves, a result stays a few MB) and at most 1/(2 workers) of the
    tosses still to hand out, so the last ones are single tosses and the workers finish together.
    """
    chunks = []
    start = 0
    while start < total:
        size = max(1, min(largest, (total - start) // (2 * workers)))
        chunks.append(range(start, start + size))
        start += size
    return chunks


def worker_context() -> multiprocessing.context.BaseContext:
    """How worker processes start: never by forking the caller, which may hold threads (torch, Hydra launchers).

    A fork server is a clean process that imports the generator (and, like "spawn", the caller's main script)
    once; workers fork from it in milliseconds, so every later variant in the same run starts its pool almost
    for free. Platforms without one get "spawn".
    """
    standard_start_method()
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["__main__", "contactbench.generation.generator"])
    return context


def _simulate_all(job: _Job, workers: int, progress: bool, description: str) -> _Chunk:
    """Every toss, in toss order, as one chunk."""
    total = sum(size for _, size in job.split_sizes)
    shape = (total, job.settings.frames, job.spec.bodies)
    everything = _Chunk(
        0,
        np.empty(shape + (7,)),
        np.empty(shape + (6,)),
        {key: np.empty(shape + (3,)) for key in CONTACT_KEYS} if job.record_contacts else {},
    )
    chunks = toss_chunks(total, workers)
    with contextlib.ExitStack() as stack:
        if workers == 1:
            runner = _TossRunner(job)
            stack.callback(runner.scene.close)
            outcomes = map(runner, chunks)
        else:
            # An executor, unlike multiprocessing.Pool, fails loudly instead of restarting workers that cannot start.
            pool = stack.enter_context(
                ProcessPoolExecutor(workers, mp_context=worker_context(), initializer=_start_worker, initargs=(job,))
            )
            # Runs first on the way out: after a failure, the chunks not started yet are dropped, not waited for.
            stack.callback(pool.shutdown, cancel_futures=True)
            futures = [pool.submit(_run_in_worker, chunk) for chunk in chunks]
            outcomes = (future.result() for future in as_completed(futures))
        bar = stack.enter_context(tqdm(total=total, desc=description, unit="toss", disable=not progress))
        # Chunks land in place as they arrive, while the workers go on with the next ones.
        for chunk in outcomes:
            rows = slice(chunk.start, chunk.start + len(chunk.poses))
            everything.poses[rows] = chunk.poses
            everything.velocities[rows] = chunk.velocities
            for key, values in chunk.contacts.items():
                everything.contacts[key][rows] = values
            bar.update(len(chunk.poses))
    return everything


def generate_dataset(
    spec: SceneSpec,
    out_dir: str | os.PathLike,
    *,
    variant: str = "",
    settings: BulletSettings = BulletSettings(),
    split_sizes: Mapping[str, int] = SPLIT_SIZES,
    seed: int = 0,
    workers: int = 2,
    record_contacts: bool = False,
    progress: bool = True,
    effects: tuple[str, ...] = (),
    effect_strength: float = 1.0,
) -> Path:
    """Simulate one scene variant and write it to `out_dir` as a recordings dataset.

    The dataset is named `spec.name`, or "<spec.name>-<variant>" when `variant` is given (e.g. "friction=0.25").
    Tosses are numbered across the splits in `split_sizes` order (train 0..274, val 275..439, test 440..549 by
    default); each has its own random stream, so the files are byte-identical for the same seed and spec
    whatever `workers` is. With record_contacts each split also holds the CONTACT_KEYS arrays [N, T, K, 3].
    `effects` (sim.effects.EFFECT_NAMES) switch on physics the meta does not describe; the tosses start
    exactly as without them, and only meta.generator.effects records what was switched on and how strongly.
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if spec.faces not in SOLID_NAMES:
        raise ValueError(f"scene {spec.name!r}: no solid with {spec.faces} faces; choose one of {sorted(SOLID_NAMES)}")
    sizes = tuple((str(name), int(size)) for name, size in split_sizes.items())
    if not sizes or any(size < 1 for _, size in sizes):
        raise ValueError(f"every split needs at least one toss, got {dict(split_sizes)}")
    solid_name = spec.shape or SOLID_NAMES[spec.faces]
    elbow = Elbow.of(spec.joint_damping, settings.width) if spec.shape == ELBOW else None
    if elbow is not None:
        mesh, pieces, solid_name = elbow.link, [], "link"
    elif spec.shape:
        mesh, pieces = nonconvex_shape(spec.shape, settings.width)
    else:
        mesh, pieces = solid(spec.faces, settings.width), []
    static_meta, static_meshes = terrain(spec.ground) if spec.ground != "flat" else ([], {})
    static = tuple((entry, static_meshes.get(entry.mesh)) for entry in static_entries(static_meta))
    derived_seed = derive_seed(seed, spec)
    concealed = ConcealedEffects.named(effects, effect_strength)
    if elbow is not None and (effects or record_contacts):
        raise ValueError("the elbow is generated without concealed effects and without contact forces")
    job = _Job(mesh, tuple(pieces), static, spec, settings, derived_seed, sizes, record_contacts, concealed, elbow)
    name = f"{spec.name}-{variant}" if variant else spec.name
    recorded = _simulate_all(job, min(workers, sum(size for _, size in sizes)), progress, name)

    splits = {}
    start = 0
    for split_name, size in sizes:
        rows = slice(start, start + size)
        splits[split_name] = Split(
            poses=recorded.poses[rows],
            lengths=np.full(size, settings.frames, dtype=np.int64),
            velocities=recorded.velocities[rows],
            extras={key: values[rows] for key, values in recorded.contacts.items()},
        )
        start += size
    mesh_path = f"meshes/{solid_name}.obj"
    piece_paths = [f"meshes/{solid_name}_piece{i}.obj" for i in range(len(pieces))]
    body_mass = settings.mass / spec.bodies if elbow is not None else settings.mass  # the elbow weighs one body
    _, inertia = mesh.mass_properties(body_mass)
    body_pieces = {"pieces": piece_paths} if pieces else {}
    meta = {
        "format": FORMAT,
        "version": SCENE_VERSION if pieces or static or elbow else VERSION,
        "name": name,
        "dt": settings.dt,
        "gravity": list(settings.gravity),
        "floor_z": 0.0,
        "bodies": [
            {
                "name": f"{solid_name}_{k}",
                "mesh": mesh_path,
                "mass": body_mass,
                "inertia_diagonal": np.diag(inertia).tolist(),
                **body_pieces,
            }
            for k in range(spec.bodies)
        ],
        **({"static": static_meta} if static_meta else {}),
        **({"joints": [elbow.joint_entry()]} if elbow else {}),
        "splits": {split_name: f"{split_name}.npz" for split_name, _ in sizes},
        "real": False,
        "generator": {
            "engine": "pybullet",
            "engine_version": importlib.metadata.version("pybullet"),
            "contactbench_version": importlib.metadata.version("contactbench"),
            "variant": variant,
            "solid": solid_name,
            "seed": int(seed),
            "derived_seed": derived_seed,
            "seeding": SEEDING,
            "split_sizes": dict(sizes),
            "settings": _plain(dataclasses.asdict(settings)),
            "scene": _plain(dataclasses.asdict(spec)),
            "engine_overrides": {
                "numSubSteps": 0,
                "deterministicOverlappingPairs": 1,
                "body_dynamics": dict(BODY_DYNAMICS_OVERRIDES),
                "inertia": "localInertiaDiagonal from the mesh, uniform density",
                "material_combination": "PyBullet multiplies the friction and the restitution of the two bodies in "
                "contact",
            },
            "contacts_recorded": record_contacts,
            "effects": concealed.truth(effects),
            "effect_strength": float(effect_strength),
        },
    }
    meshes = {mesh_path: mesh, **dict(zip(piece_paths, pieces)), **static_meshes}
    return write_recordings(out_dir, Recordings(meta=meta, meshes=meshes, splits=splits))


def _plain(fields: dict) -> dict:
    """Dataclass fields as JSON values (tuples become lists)."""
    return {key: list(value) if isinstance(value, tuple) else value for key, value in fields.items()}
