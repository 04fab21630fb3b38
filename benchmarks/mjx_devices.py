"""sysid_mjx's step (eq. 1 over 16-frame windows of the real cube and its jacfwd gradient) timed on every jax device
of a machine: the GPU against the same machine's CPU, in the same run.

Two halves, so the timing runs where only jax and mujoco-mjx are installed (a lent GPU machine's image):
  python benchmarks/mjx_devices.py prepare FOLDER            # here: the scene and the windows, from contactbench
  python benchmarks/mjx_devices.py time FOLDER gpu cpu       # anywhere: compile and median step time per device
The timing half restates models/sysid/gradient.py's loss (eq. 1, p = 2, over the windows) in a few lines for that
reason: it must not import contactbench.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

SIZES = (64, 1024)
CUBE_DATA = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"


def prepare(folder: Path) -> None:
    from contactbench.models.sysid.gradient import BoxCoordinates, MjxWindows
    from contactbench.models.sysid.search_space import SearchSpace
    from contactbench.recordings import read_recordings
    from contactbench.sim.mujoco_scene import scene_xml

    folder.mkdir(parents=True, exist_ok=True)
    cube = read_recordings(CUBE_DATA)
    space = SearchSpace(1)
    box = BoxCoordinates(space)
    (folder / "scene.xml").write_text(scene_xml(cube.scene, space.from_vector(box.to_vector(box.start))))
    sampler = MjxWindows.__new__(MjxWindows)  # its window sampling only: no jax here
    sampler.context_frames, sampler.window_frames = 6, 16
    for n in SIZES:
        qpos, qvel, truth, scored = sampler.windows(cube.split("train"), cube.dt, n, np.random.default_rng(n))
        np.savez(
            folder / f"windows_{n}.npz",
            qpos=qpos,
            qvel=qvel,
            truth=truth,
            scored=scored,
            widths=cube.widths(),
            start=box.start,
            low=box.low,
            high=box.high,
            logarithmic=box.logarithmic,
        )


def time_devices(folder: Path, backends: list[str], sizes=SIZES) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    import mujoco
    from jax import numpy as jnp
    from mujoco import mjx

    print("jax", jax.__version__, "mujoco", mujoco.__version__, "devices", jax.devices(), flush=True)
    model = mujoco.MjModel.from_xml_string((folder / "scene.xml").read_text())
    results = []
    for backend in backends:
        device = jax.devices(backend)[0]
        for n in sizes:
            data = dict(np.load(folder / f"windows_{n}.npz"))
            low, high, logarithmic = data["low"], data["high"], data["logarithmic"]
            widths = jnp.asarray(data["widths"])
            with jax.default_device(device):
                reference = mjx.put_model(model, device=device)

                def simulated(u, reference=reference, low=low, high=high, logarithmic=logarithmic):
                    inside = low + (high - low) / (1 + jnp.exp(-u))
                    v = jnp.where(logarithmic, jnp.exp(inside), inside)
                    sliding = jnp.maximum(v[0], v[1])
                    return reference.replace(
                        pair_friction=reference.pair_friction.at[:, 0].set(sliding).at[:, 1].set(sliding),
                        pair_solref=jnp.stack([-v[2:3], -v[3:4]], axis=-1),
                    )

                def rollout(m, qpos, qvel):
                    d = mjx.make_data(m).replace(qpos=qpos, qvel=qvel)

                    def frame(d, _):
                        d = mjx.step(m, d)
                        return d, d.qpos

                    return jax.lax.scan(frame, d, None, length=16)[1]

                def loss(u, qpos, qvel, truth, scored, widths=widths):
                    poses = jax.vmap(rollout, in_axes=(None, 0, 0))(simulated(u), qpos, qvel).reshape(truth.shape)
                    offset = poses[..., :3] - truth[..., :3]
                    positional = jnp.sum(offset * offset, axis=-1) @ (2.0 / widths) ** 2
                    dot = jnp.sum(poses[..., 3:] * truth[..., 3:], axis=-1)
                    norms = jnp.sum(poses[..., 3:] ** 2, axis=-1) * jnp.sum(truth[..., 3:] ** 2, axis=-1)
                    angle = 2.0 * jnp.arctan2(jnp.sqrt(jnp.maximum(norms - dot * dot, 0.0) + 1e-12), jnp.abs(dot))
                    errors = jnp.where(scored, positional + jnp.sum(angle * angle, axis=-1), 0.0)
                    return jnp.mean(jnp.sum(errors, axis=-1) / jnp.sum(scored, axis=-1))

                def value_and_gradient(u, *windows):
                    gradient, value = jax.jacfwd(lambda u: (loss(u, *windows),) * 2, has_aux=True)(u)
                    return value, gradient

                step = jax.jit(value_and_gradient)
                args = [
                    jax.device_put(jnp.asarray(data[k]), device) for k in ("start", "qpos", "qvel", "truth", "scored")
                ]
                started = time.perf_counter()
                value, gradient = jax.block_until_ready(step(*args))
                compile_s = time.perf_counter() - started
                times = []
                for _ in range(5):
                    started = time.perf_counter()
                    jax.block_until_ready(step(*args))
                    times.append(time.perf_counter() - started)
                row = {
                    "backend": backend,
                    "windows": n,
                    "compile_s": compile_s,
                    "step_s": float(np.median(times)),
                    "loss": float(value),
                    "gradient": np.asarray(gradient).tolist(),
                }
                print(json.dumps(row), flush=True)
                results.append(row)
    for n in sizes:
        by_backend = {row["backend"]: row["step_s"] for row in results if row["windows"] == n}
        if "gpu" in by_backend and "cpu" in by_backend:
            print(
                f"{n} windows: GPU step {by_backend['gpu']:.3f} s, CPU step {by_backend['cpu']:.3f} s, "
                f"ratio CPU / GPU {by_backend['cpu'] / by_backend['gpu']:.1f}"
            )


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("prepare", "time"):
        sys.exit(__doc__)
    if sys.argv[1] == "prepare":
        prepare(Path(sys.argv[2]))
    else:
        time_devices(Path(sys.argv[2]), sys.argv[3:] or ["cpu"])
