"""MJX, MuJoCo's JAX port, for the models that differentiate through it: the import, a reverse-mode solver, eq. (1).

jax is imported here and only by the models that ask for it (sysid_mjx, the residual with `gradient: mjx`).
"""

from __future__ import annotations

import contextlib
import io
import logging
from collections.abc import Iterator


def import_mjx():
    """(jax, jax.numpy, mjx), jax switched to 64-bit: the rollouts compare millimetres over seconds."""
    import jax

    jax.config.update("jax_enable_x64", True)
    with contextlib.redirect_stdout(io.StringIO()):  # mjx prints "Failed to import warp" (its GPU back-end)
        from mujoco import mjx
    logging.getLogger().addFilter(quiet_device_lines)
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "Unable to initialize backend 'tpu'"
    return jax, jax.numpy, mjx


def quiet_device_lines(record: logging.LogRecord) -> bool:
    """MJX logs "Using JAX default device" on the root logger at every model it places or traces: noise in a run's
    log."""
    return not (record.name == "root" and str(record.msg).startswith("Using JAX default device"))


@contextlib.contextmanager
def scanned_solver(iterations: int) -> Iterator[None]:
    """While active (wrap every call of a jit function: it traces on first use), MJX's constraint solver loops by
    `scan` for exactly `iterations`, finished iterations as no-ops: reverse mode differentiates a scan, not MJX's
    `while_loop`. The model's own `opt.iterations` should be the same cap (its stopping test reads it)."""
    import jax
    from mujoco.mjx._src import solver

    class Lax:
        def __getattr__(self, name):
            return getattr(jax.lax, name)

        @staticmethod
        def while_loop(cond, body, state):
            return solver._while_loop_scan(cond, body, state, iterations)

    class Jax:
        lax = Lax()

        def __getattr__(self, name):
            return getattr(jax, name)

    original = solver.jax
    solver.jax = Jax()
    try:
        yield
    finally:
        solver.jax = original


def truncated(jax, tree, frame, every: int | None):
    """A rollout's carried state at `frame` (a traced index), its gradient path cut every `every` frames: a long
    rollout keeps its states (the model's own, as in val) while each gradient reaches back at most `every` frames,
    not through a whole chaotic toss. None: never cut."""
    if every is None:
        return tree
    cut = frame % every == 0
    return jax.tree.map(lambda leaf: jax.numpy.where(cut, jax.lax.stop_gradient(leaf), leaf), tree)


def pose_loss(jnp, poses, truth, scored, widths, position_exponent: int):
    """Eq. (1) in jax.numpy: poses and truth [W, T, K, 7], scored [W, T] -> the mean over windows of each window's
    mean over its scored frames of sum over bodies of (position error in half-widths)^p + (rotation angle)^2."""
    offset = poses[..., :3] - truth[..., :3]
    positional = jnp.sum(offset * offset, axis=-1) @ (2.0 / widths) ** position_exponent
    dot = jnp.sum(poses[..., 3:] * truth[..., 3:], axis=-1)
    norms = jnp.sum(poses[..., 3:] ** 2, axis=-1) * jnp.sum(truth[..., 3:] ** 2, axis=-1)
    # 1e-12 under the root: the angle's derivative is infinite at zero error
    angle = 2.0 * jnp.arctan2(jnp.sqrt(jnp.maximum(norms - dot * dot, 0.0) + 1e-12), jnp.abs(dot))
    errors = jnp.where(scored, positional + jnp.sum(angle * angle, axis=-1), 0.0)
    return jnp.mean(jnp.sum(errors, axis=-1) / jnp.maximum(jnp.sum(scored, axis=-1), 1))  # every window counts once
