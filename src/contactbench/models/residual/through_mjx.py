"""The residual correction differentiated through MJX: eq. (1) over rollout windows, backpropagated through every step.

`ResidualModule` with `gradient: mjx` trains its network on this instead of MuJoCo's finite-difference
linearisation: the identified MuJoCo model runs in MJX (MuJoCo's JAX port), the correction of `correction.py`
(features, network, the projection that keeps it from pushing into the floor or adding energy, the integration) is
written here in jax.numpy step for step, and `jax.value_and_grad` gives the exact gradient of the window loss with
respect to the network's weights, through the contact solver and through the features' own dependence on the
state (which the linearised adjoint leaves out). `tests/test_residual_mjx.py` holds the two versions equal.

Reverse mode cannot pass MJX's solver `while_loop`; `scanned_solver` swaps it for MJX's own scan form with a fixed
cap (`solver_iterations`, 10: C MuJoCo's solver needs at most 9 iterations on these tosses, and MJX capped at 4
is wrong; docs/DIFFERENTIABLE.md) while the loss is traced. The network trained here is the torch network the
C-MuJoCo rollout uses: weights go in, gradients come out.
"""

from __future__ import annotations

import numpy as np

from contactbench.models.residual.correction import LOWEST_VERTICES, NEIGHBOUR_FEATURES, Bodies
from contactbench.scene import Scene
from contactbench.sim.mjx import import_mjx, pose_loss, scanned_solver, truncated
from contactbench.sim.mujoco_scene import ContactParameters, build_model

STANDARDISATION = ("feature_mean", "feature_std", "target_std")  # the module's buffers the network reads


class JaxCorrection:
    """correction.py's step in jax.numpy, for one state [K, 7] / [K, 6] (vmap batches it)."""

    def __init__(self, jnp, bodies: Bodies, contact_margin: float, max_correction: float):
        self.jnp = jnp
        self.vertices = [jnp.asarray(v) for v in bodies.vertices]
        self.masses, self.com, self.inertia = map(jnp.asarray, (bodies.masses, bodies.com, bodies.inertia))
        self.offset_com = bool(np.any(bodies.com))
        self.floor_z, self.dt = bodies.floor_z, bodies.dt
        self.gravity = jnp.asarray(bodies.gravity / np.linalg.norm(bodies.gravity))
        self.contact_margin, self.max_correction = contact_margin, max_correction

    # quaternions (w, x, y, z), as rotations.py
    def rotate(self, q, v):
        w, u = q[..., :1], q[..., 1:]
        t = 2.0 * self.jnp.cross(u, v)
        return v + w * t + self.jnp.cross(u, t)

    def to_body(self, q, v):
        return self.rotate(q * self.jnp.array([1.0, -1.0, -1.0, -1.0]), v)

    def multiply(self, a, b):
        aw, ax, ay, az = (a[..., i] for i in range(4))
        bw, bx, by, bz = (b[..., i] for i in range(4))
        return self.jnp.stack(
            [
                aw * bw - ax * bx - ay * by - az * bz,
                aw * bx + ax * bw + ay * bz - az * by,
                aw * by - ax * bz + ay * bw + az * bx,
                aw * bz + ax * by - ay * bx + az * bw,
            ],
            axis=-1,
        )

    def from_rotation_vector(self, rotvec):
        jnp = self.jnp
        squared = jnp.sum(rotvec * rotvec, axis=-1, keepdims=True)
        angle = jnp.sqrt(jnp.maximum(squared, 1e-30))  # finite derivative at zero rotation
        scale = jnp.where(squared > 1e-24, jnp.sin(angle / 2) / angle, 0.5)
        return jnp.concatenate([jnp.cos(angle / 2), scale * rotvec], axis=-1)

    def placed(self, qpos, k):
        return qpos[k, :3] + self.rotate(qpos[k, 3:], self.vertices[k])

    def vertical_velocities(self, q, qvel, offset):
        """World vertical velocity [V] of points at world offsets [V, 3] for one body velocity qvel [6]."""
        omega = self.rotate(q, qvel[3:])
        return qvel[2] + omega[0] * offset[:, 1] - omega[1] * offset[:, 0]

    def kinetic_energy(self, qpos, qvel):
        """[K] as correction.kinetic_energy."""
        jnp = self.jnp
        linear, angular = qvel[:, :3], qvel[:, 3:]
        if self.offset_com:
            linear = linear + self.rotate(qpos[:, 3:], jnp.cross(angular, self.com))
        translational = self.masses * jnp.sum(linear * linear, axis=-1)
        rotational = jnp.einsum("ki,kij,kj->k", angular, self.inertia, angular)
        return 0.5 * (translational + rotational)

    def features(self, qpos0, qvel0, qpos1, qvel1):
        """[K, F] as correction.features."""
        jnp = self.jnp
        q0 = qpos0[:, 3:]
        parts = [
            self.to_body(q0, jnp.broadcast_to(self.gravity, (len(q0), 3))),
            qpos0[:, 2:3] - self.floor_z,
            self.to_body(q0, qvel0[:, :3]),
            qvel0[:, 3:],
            self.to_body(q0, qvel1[:, :3] - qvel0[:, :3]),
            qvel1[:, 3:] - qvel0[:, 3:],
            self.lowest_vertices(qpos0, qvel0),
            self.nearest_neighbour(qpos0, qvel0),
        ]
        return jnp.concatenate(parts, axis=-1)

    def lowest_vertices(self, qpos, qvel):
        jnp = self.jnp
        out = []
        for k, vertices in enumerate(self.vertices):
            placed = self.placed(qpos, k)
            order = jnp.argsort(placed[:, 2])[:LOWEST_VERTICES]
            lowest = placed[order]
            vertical = self.vertical_velocities(qpos[k, 3:], qvel[k], lowest - qpos[k, :3])
            out.append(jnp.concatenate([lowest[:, 2] - self.floor_z, vertical, vertices[order].reshape(-1)]))
        return jnp.stack(out)

    def nearest_neighbour(self, qpos, qvel):
        jnp = self.jnp
        n_bodies = len(self.vertices)
        if n_bodies < 2:
            return jnp.zeros((n_bodies, NEIGHBOUR_FEATURES))
        position = qpos[:, :3]
        offsets = position[None, :, :] - position[:, None, :]  # [K, K, 3]: other - own
        distance = jnp.sqrt(jnp.sum(offsets * offsets, axis=-1) + jnp.eye(n_bodies))  # no zero under the root
        distance = jnp.where(jnp.eye(n_bodies, dtype=bool), jnp.inf, distance)
        nearest = jnp.argmin(distance, axis=-1)
        rows = jnp.arange(n_bodies)
        q = qpos[:, 3:]
        return jnp.concatenate(
            [
                self.to_body(q, offsets[rows, nearest]),
                self.to_body(q, qvel[nearest, :3] - qvel[:, :3]),
                distance[rows, nearest][:, None],
            ],
            axis=-1,
        )

    def allowed_fraction(self, qpos1, qvel1, change, energy_limit):
        """[K] as correction.allowed_fraction (divisions guarded so that no branch's derivative is infinite)."""
        jnp = self.jnp
        fractions = []
        for k in range(len(self.vertices)):
            placed = self.placed(qpos1, k)
            offset = placed - qpos1[k, :3]
            near = placed[:, 2] - self.floor_z < self.contact_margin
            rising = self.vertical_velocities(qpos1[k, 3:], qvel1[k], offset)
            pushed = self.vertical_velocities(qpos1[k, 3:], change[k], offset)
            blocking = near & (pushed < 0)
            limit = jnp.where(blocking, (jnp.minimum(rising, 0.0) - rising) / jnp.where(blocking, pushed, -1.0), 1.0)
            fractions.append(jnp.clip(jnp.min(limit), 0.0, 1.0))
        fraction = jnp.stack(fractions)
        c = self.kinetic_energy(qpos1, qvel1)
        a = self.kinetic_energy(qpos1, change)
        b = self.kinetic_energy(qpos1, qvel1 + change) - a - c
        slack = jnp.maximum(energy_limit - c, 0.0)
        positive = a > 0
        root = jnp.where(
            positive,
            (-b + jnp.sqrt(jnp.maximum(b * b + 4 * a * slack, 1e-30))) / (2 * jnp.where(positive, a, 1.0)),
            1.0,
        )
        return jnp.minimum(fraction, jnp.clip(root, 0.0, 1.0))

    def corrected(self, qpos0, qvel0, qpos1, qvel1, body_correction):
        """MuJoCo's post-step state with the projected correction applied and integrated, as correction.corrected."""
        jnp = self.jnp
        change = jnp.concatenate([self.rotate(qpos1[:, 3:], body_correction[:, :3]), body_correction[:, 3:]], -1)
        limit = jnp.maximum(self.kinetic_energy(qpos0, qvel0), self.kinetic_energy(qpos1, qvel1))
        change = change * self.allowed_fraction(qpos1, qvel1, change, limit)[:, None]
        turned = self.multiply(qpos1[:, 3:], self.from_rotation_vector(self.dt * change[:, 3:]))
        quaternion = turned / jnp.linalg.norm(turned, axis=-1, keepdims=True)
        return jnp.concatenate([qpos1[:, :3] + self.dt * change[:, :3], quaternion], -1), qvel1 + change

    def network(self, weights, inputs):
        """ResidualModule.forward in jax.numpy: weights [(W, b), ...] of Linear layers with SiLU between, inputs
        standardised by the module's buffers, outputs scaled by target_std and clipped to max_correction of it."""
        jnp = self.jnp
        (feature_mean, feature_std, target_std), layers = weights[0], weights[1:]
        hidden = (inputs - feature_mean) / feature_std
        for index, (matrix, bias) in enumerate(layers):
            hidden = hidden @ matrix.T + bias
            if index < len(layers) - 1:
                hidden = hidden * (1.0 / (1.0 + jnp.exp(-hidden)))
        return target_std * jnp.clip(hidden, -self.max_correction, self.max_correction)


class MjxResidualWindows:
    """The corrected MJX rollout of windows from recorded states, eq. (1) against the recording, and its gradient
    with respect to the network's weights (jit-compiled once per window shape)."""

    def __init__(
        self,
        dataset: Scene,
        parameters: ContactParameters,
        contact_margin: float,
        max_correction: float,
        solver_iterations: int,
        substeps: int = 1,
        truncation: int | None = None,
    ):
        jax, jnp, mjx = import_mjx()
        self.jnp = jnp
        self.solver_iterations = solver_iterations
        model = build_model(dataset, parameters, substeps)
        model.opt.iterations = solver_iterations
        mjx_model = mjx.put_model(model)
        step = JaxCorrection(jnp, Bodies.of(dataset), contact_margin, max_correction)
        n_bodies = dataset.n_bodies
        widths = jnp.asarray(dataset.widths())

        def rollout(weights, qpos, qvel, frames: int):
            data = mjx.make_data(mjx_model).replace(qpos=qpos.reshape(-1), qvel=qvel.reshape(-1))

            def frame(carry, index):
                data, qpos, qvel = carry
                data, qpos, qvel = truncated(jax, (data, qpos, qvel), index, truncation)
                data = data.replace(qpos=qpos.reshape(-1), qvel=qvel.reshape(-1))
                data = jax.lax.fori_loop(0, substeps, lambda _, d: mjx.step(mjx_model, d), data)
                qpos1, qvel1 = data.qpos.reshape(n_bodies, 7), data.qvel.reshape(n_bodies, 6)
                inputs = step.features(qpos, qvel, qpos1, qvel1)
                qpos, qvel = step.corrected(qpos, qvel, qpos1, qvel1, step.network(weights, inputs))
                return (data, qpos, qvel), qpos

            return jax.lax.scan(frame, (data, qpos, qvel), jnp.arange(frames))[1]

        def loss(weights, qpos, qvel, truth, scored):
            batched = jax.vmap(rollout, in_axes=(None, 0, 0, None))
            poses = batched(weights, qpos, qvel, truth.shape[1])
            return pose_loss(jnp, poses, truth, scored, widths, position_exponent=2)

        self._value_and_gradient = jax.jit(jax.value_and_grad(loss))

    @staticmethod
    def weights(module) -> list:
        """The residual module's buffers and Linear layers as numpy arrays, in `JaxCorrection.network`'s order."""
        buffers = tuple(module.get_buffer(name).detach().double().cpu().numpy() for name in STANDARDISATION)
        layers = [
            (layer.weight.detach().double().cpu().numpy(), layer.bias.detach().double().cpu().numpy())
            for layer in module.network
            if hasattr(layer, "weight")
        ]
        return [buffers, *layers]

    def value_and_gradient(self, weights, qpos, qvel, truth, scored) -> tuple[float, list]:
        """The window loss and its gradient [(dW, db), ...] for the Linear layers (the buffers' are dropped)."""
        with scanned_solver(self.solver_iterations):
            value, gradient = self._value_and_gradient(weights, *map(self.jnp.asarray, (qpos, qvel, truth, scored)))
        return float(value), [tuple(np.array(part) for part in layer) for layer in gradient[1:]]
