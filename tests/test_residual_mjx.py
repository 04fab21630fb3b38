"""The residual correction through MJX (model.module.gradient=mjx): its jax.numpy step equals correction.py's, and the
module's gradient is reverse mode through MJX's scanned solver, the window loss's slope."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.models.residual import correction
from contactbench.models.residual.correction import Bodies
from contactbench.models.residual.module import ResidualModule
from contactbench.models.residual.through_mjx import JaxCorrection, MjxResidualWindows
from contactbench.models.residual.windows import recorded_windows
from contactbench.recordings import read_recordings
from contactbench.sim.mjx import import_mjx

REAL_CUBE = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"
IDENTIFIED = np.array([0.19, 0.21, 7500.0, 144.0])  # near what NGOpt finds on the real cube at budget=quick


def two_bodies() -> Bodies:
    """A cube about its centre and a box whose mesh frame is off its centre of mass, on the floor."""
    cube = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
    return Bodies(
        vertices=(cube, cube * [1.0, 0.6, 0.4] + [0.01, 0.0, 0.02]),
        masses=np.array([0.37, 0.2]),
        com=np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.02]]),
        inertia=np.stack([np.eye(3) * 6e-4, np.diag([2e-4, 3e-4, 4e-4])]),
        floor_z=0.0,
        gravity=np.array([0.0, 0.0, -9.81]),
        dt=1 / 148,
    )


def test_the_jax_step_is_correction_pys_step_to_rounding():
    """Features, the projection (near-floor vertices, energy) and the integration, for two bodies at random states
    near the floor with corrections large enough that the projection acts."""
    jax, jnp, _ = import_mjx()
    bodies = two_bodies()
    rng = np.random.default_rng(0)
    n = 64
    qpos0 = np.concatenate([rng.uniform(-0.1, 0.1, (n, 2, 2)), rng.uniform(0.0, 0.08, (n, 2, 1))], axis=-1)
    qpos0 = np.concatenate([qpos0, rotations.uniform_random(rng, 2 * n).reshape(n, 2, 4)], axis=-1)
    qvel0 = rng.normal(scale=0.5, size=(n, 2, 6))
    qpos1 = qpos0 + np.concatenate([rng.normal(scale=3e-3, size=(n, 2, 3)), np.zeros((n, 2, 4))], axis=-1)
    qvel1 = qvel0 + rng.normal(scale=0.2, size=(n, 2, 6))
    change = rng.normal(scale=1.0, size=(n, 2, 6))
    step = JaxCorrection(jnp, bodies, contact_margin=0.01, max_correction=4.0)
    states = tuple(map(jnp.asarray, (qpos0, qvel0, qpos1, qvel1)))
    np.testing.assert_allclose(
        np.asarray(jax.vmap(step.features)(*states)),
        correction.features(bodies, qpos0, qvel0, qpos1, qvel1),
        atol=1e-12,
    )
    projected, fraction = correction.projected_change(bodies, qpos0, qvel0, qpos1, qvel1, change, 0.01)
    assert 0.2 < np.mean(fraction < 1) < 1.0  # the projection acted on some bodies, not on all
    expected = correction.corrected(bodies, qpos0, qvel0, qpos1, qvel1, change, 0.01)
    found = jax.vmap(step.corrected)(*states, jnp.asarray(change))
    for ours, theirs in zip(found, expected):
        np.testing.assert_allclose(np.asarray(ours), theirs, atol=1e-12)


def test_the_jax_network_is_the_modules_network():
    dataset = read_recordings(REAL_CUBE, ["train"])
    module = ResidualModule(dataset, 6, sysid={}, hidden=(32, 32))
    torch.manual_seed(0)
    for parameter in module.network.parameters():
        torch.nn.init.normal_(parameter, std=0.3)
    module.feature_mean.normal_()
    module.feature_std.uniform_(0.5, 2.0)
    module.target_std.uniform_(0.1, 1.0)
    jax, jnp, _ = import_mjx()
    step = JaxCorrection(jnp, Bodies.of(dataset), 0.01, module.hparams.max_correction)
    inputs = np.random.default_rng(1).normal(size=(50, module.bodies.n_features))
    weights = jax.tree.map(jnp.asarray, MjxResidualWindows.weights(module))
    ours = np.asarray(jax.vmap(step.network, in_axes=(None, 0))(weights, jnp.asarray(inputs)))
    expected = module(torch.as_tensor(inputs, dtype=torch.float32)).detach().numpy()
    np.testing.assert_allclose(ours, expected, rtol=1e-5, atol=1e-6)
    bound = 4.0 * module.target_std.numpy()
    assert np.isclose(np.abs(expected), bound, rtol=1e-6).any()  # some outputs clipped: the clip is the same too


@pytest.mark.slow
def test_the_modules_gradient_is_reverse_mode_through_mjx_and_the_window_losss_slope():
    """Real cube windows from recorded states, the identified MuJoCo in MJX with a random correction: the surrogate
    the module trains on carries jax.grad through the scanned solver into the torch weights, and that gradient agrees
    with central differences of the same loss on the last layer's bias."""
    dataset = read_recordings(REAL_CUBE, ["train"])
    module = ResidualModule(dataset, 6, sysid={}, hidden=(16,), unroll=3, gradient="mjx")
    module.parameters_vector.copy_(torch.as_tensor(IDENTIFIED))
    torch.manual_seed(0)
    torch.nn.init.normal_(module.network[-1].weight, std=0.1)
    module.feature_std.fill_(1.0)
    module.target_std.fill_(0.05)
    segments = torch.as_tensor(np.stack([np.arange(8), np.arange(8) * 5], axis=1))
    loss = module.window_loss("train", segments)
    loss.backward()
    bias_gradient = module.network[-1].bias.grad.numpy().astype(float)
    assert np.isfinite(loss.item()) and np.abs(bias_gradient).max() > 0

    windows = recorded_windows(dataset.split("train"), segments.numpy(), 3, dataset.dt)
    assert windows[3].all()  # every frame of these windows is recorded
    weights = MjxResidualWindows.weights(module)
    step = 1e-5
    for index in range(6):
        shifted = []
        for sign in (1, -1):
            bias = weights[-1][1].copy()
            bias[index] += sign * step
            moved = [*weights[:-1], (weights[-1][0], bias)]
            shifted.append(module._mjx_windows.value_and_gradient(moved, *windows)[0])
        slope = (shifted[0] - shifted[1]) / (2 * step)
        assert bias_gradient[index] == pytest.approx(slope, rel=1e-3, abs=1e-6 * loss.item())


def test_an_unknown_gradient_or_a_bad_cut_is_refused_in_one_line():
    dataset = read_recordings(REAL_CUBE, ["train"])
    with pytest.raises(ContactbenchError, match=r"gradient is 'adjoint' \(expected one of linearised, mjx"):
        ResidualModule(dataset, 6, sysid={}, gradient="adjoint")
    for name, value in (("truncation", 0), ("solver_iterations", 2.5)):
        with pytest.raises(ContactbenchError, match=f"model.module.{name} is {value!r} \\(expected a positive integer"):
            ResidualModule(dataset, 6, sysid={}, gradient="mjx", **{name: value})


def test_truncation_keeps_the_rollout_and_cuts_its_gradient_every_n_frames():
    """x_{t+1} = a x_t from x_0 = 1 over 6 frames, loss x_6 = a^6: cut every 2 frames, only the last 2 steps carry a
    (the state at frame 4 is taken as given), so d/da is 2 a x_4 = 2 a^5 while the value stays a^6."""
    from contactbench.sim.mjx import truncated

    jax, jnp, _ = import_mjx()

    def final(a, every):
        def frame(x, index):
            x = truncated(jax, x, index, every) * a
            return x, x

        return jax.lax.scan(frame, jnp.asarray(1.0), jnp.arange(6))[0]

    a = 1.1
    for every, slope in ((None, 6 * a**5), (2, 2 * a**5), (1, a**5), (4, 2 * a**5)):
        value, gradient = jax.value_and_grad(final)(a, every)
        assert float(value) == pytest.approx(a**6) and float(gradient) == pytest.approx(slope)
