"""MJX, MuJoCo's JAX port, for the models that differentiate through it: the import, which scenes it simulates, the
constants MuJoCo's compiler derives from inertia, a reverse-mode solver, eq. (1).

jax is imported here and only by the models that ask for it (sysid_mjx, the residual with `gradient: mjx`).
"""

from __future__ import annotations

import contextlib
import io
import logging
from collections.abc import Iterator

import mujoco
import numpy as np

from contactbench.errors import NotApplicable
from contactbench.scene import Scene
from contactbench.sim.mujoco_scene import ContactParameters, build_model


def import_mjx():
    """(jax, jax.numpy, mjx), jax switched to 64-bit: the rollouts compare millimetres over seconds."""
    import jax

    jax.config.update("jax_enable_x64", True)
    with contextlib.redirect_stdout(io.StringIO()):  # mjx prints "Failed to import warp" (its GPU back-end)
        from mujoco import mjx
    logging.getLogger().addFilter(quiet_device_lines)
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "Unable to initialize backend 'tpu'"
    return jax, jax.numpy, mjx


def require_mjx(scene: Scene) -> None:
    """NotApplicable (one line) for a scene MJX cannot simulate: its MuJoCo model as scene_xml writes it (free and
    hinged bodies, convex pieces, static meshes and height fields) with anything MJX's put_model refuses. Terrain and
    non-convex bodies are refused before that: put_model takes them, but their rollouts have not been checked against
    C MuJoCo's as free and hinged convex bodies on the flat floor have (tests/test_sysid_mjx.py)."""
    if scene.static or not all(scene.is_convex(k) for k in range(scene.n_bodies)):
        raise NotApplicable(
            f"MJX here simulates free and hinged convex bodies on the flat floor; {scene.name} has terrain or "
            "non-convex bodies (model=sysid simulates those)"
        )
    _, _, mjx = import_mjx()
    model = build_model(scene, ContactParameters.mujoco_default(scene.n_bodies))
    try:
        mjx.put_model(model)
    except (NotImplementedError, ValueError) as error:
        message = " ".join(str(error).split()) or type(error).__name__
        raise NotApplicable(f"MJX cannot simulate {scene.name}'s MuJoCo model: {message}") from error


def inertia_constants(model: mujoco.MjModel, jnp, mjx):
    """MJX model -> {body_invweight0, dof_invweight0} computed from its inertia as MuJoCo's compiler does
    (mj_setConst, at qpos0: each body's mean translational and rotational diagonal of J M^-1 J^T at its centre of
    mass, each dof's diagonal of M^-1, a free joint's averaged over its 3 translations and its 3 rotations). They set
    the constraints' regularisation, so a model whose inertia changes in jax must carry them along. `model` is the
    compiled MuJoCo model it was put from (its structure: which dofs average together)."""
    averaging = np.eye(model.nv)
    for joint in range(model.njnt):
        if model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE:
            for block in (0, 3):
                dofs = model.jnt_dofadr[joint] + block + np.arange(3)
                averaging[np.ix_(dofs, dofs)] = 1 / 3
        elif model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_BALL:
            dofs = model.jnt_dofadr[joint] + np.arange(3)
            averaging[np.ix_(dofs, dofs)] = 1 / 3
    bodies = np.arange(1, model.nbody)

    def constants(mjx_model) -> dict:
        data = mjx.make_data(mjx_model)
        data = mjx.crb(mjx_model, mjx.com_pos(mjx_model, mjx.kinematics(mjx_model, data)))
        inverse = jnp.linalg.inv(mjx.full_m(mjx_model, data))

        def body(index):
            translation, rotation = mjx.jac(mjx_model, data, data.xipos[index], index)  # [nv, 3] each
            weights = jnp.concatenate([translation, rotation], axis=1)
            diagonal = jnp.einsum("ij,ik,kj->j", weights, inverse, weights)
            return jnp.stack([jnp.mean(diagonal[:3]), jnp.mean(diagonal[3:])])

        weights = jnp.concatenate([jnp.zeros((1, 2)), jnp.stack([body(int(b)) for b in bodies])])
        return {"body_invweight0": weights, "dof_invweight0": jnp.asarray(averaging) @ jnp.diagonal(inverse)}

    return constants


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
