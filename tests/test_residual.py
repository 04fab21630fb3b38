"""Tests of the residual model: its step physics (target, projection, energy), the rollout gradient, the pipeline."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from conftest import falling_cubes
from test_pipeline import compose_config

from contactbench import rotations, runs
from contactbench.config import REPO_ROOT
from contactbench.kinematics import world_vertices
from contactbench.models.residual import correction
from contactbench.models.residual.contact_model import ResidualContactModel
from contactbench.models.residual.correction import Bodies
from contactbench.models.residual.module import ResidualModule
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.sim.mujoco_scene import ContactParameters, body_frame_velocities
from contactbench.sim.rollout import MujocoRollouts, rollout_context

PARAMETERS = ContactParameters(object_friction=(0.2,), floor_friction=0.2, floor_stiffness=2000.0, floor_damping=40.0)


@pytest.fixture(scope="module")
def real_cube():
    return read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["val"])


def step_from_recorded(dataset, frame: int):
    split = dataset.split("val")
    qpos0 = split.poses[:, frame].copy()
    qpos0[..., 3:] = rotations.normalize(qpos0[..., 3:])
    qvel0 = body_frame_velocities(qpos0, split.velocities[:, frame])
    n = len(qpos0)
    qpos1, qvel1, _ = MujocoRollouts(dataset).step(PARAMETERS, qpos0.reshape(n, -1), qvel0.reshape(n, -1))
    return qpos0, qvel0, qpos1.reshape(n, 1, 7), qvel1.reshape(n, 1, 6)


def test_the_target_correction_puts_a_step_on_the_recorded_next_pose(real_cube):
    bodies = Bodies.of(real_cube)
    qpos0, qvel0, qpos1, qvel1 = step_from_recorded(real_cube, 20)
    recorded = real_cube.split("val").poses[:, 21]
    wanted = correction.targets(qpos0, qpos1, qvel1, recorded, bodies.dt)
    change = np.concatenate([rotations.rotate(qpos1[..., 3:], wanted[..., :3]), wanted[..., 3:]], axis=-1)
    qpos, _ = correction.integrate(bodies, qpos1, qvel1, change)
    assert np.abs(qpos[..., :3] - recorded[..., :3]).max() < 1e-12
    before = rotations.angle_between(qpos1[..., 3:], recorded[..., 3:]).max()
    after = rotations.angle_between(qpos[..., 3:], recorded[..., 3:]).max()
    assert before > 0.01 and after < before / 10  # first order in dt: exp(a) exp(b) ~ exp(a + b)


def test_only_the_step_change_columns_describe_mujocos_step(real_cube):
    bodies = Bodies.of(real_cube)
    qpos0, qvel0, qpos1, qvel1 = step_from_recorded(real_cube, 20)
    stepped = correction.features(bodies, qpos0, qvel0, qpos1, qvel1)
    unstepped = correction.features(bodies, qpos0, qvel0, qpos0, qvel0)
    assert np.all(unstepped[..., correction.STEP_CHANGE] == 0)
    assert np.abs(stepped[..., correction.STEP_CHANGE]).max() > 1e-3
    others = np.ones(bodies.n_features, dtype=bool)
    others[correction.STEP_CHANGE] = False
    np.testing.assert_array_equal(stepped[..., others], unstepped[..., others])


def sliding_cube(bodies: Bodies, speed: float = 1.0):
    """A cube flat on the floor sliding along x, before and after a MuJoCo step."""
    half = bodies.vertices[0][:, 2].max()
    qpos0 = np.array([[[0.0, 0.0, half - 1e-4, 1.0, 0.0, 0.0, 0.0]]])
    qvel0 = np.array([[[speed, 0.0, 0.0, 0.0, 0.0, 0.0]]])
    qpos1 = qpos0 + np.array([speed * bodies.dt, 0, 0, 0, 0, 0, 0])
    qvel1 = qvel0 * 0.98
    return qpos0, qvel0, qpos1, qvel1


def test_a_correction_never_drives_a_floor_contact_down_nor_adds_kinetic_energy(real_cube):
    bodies = Bodies.of(real_cube)
    qpos0, qvel0, qpos1, qvel1 = sliding_cube(bodies)
    rng = np.random.default_rng(0)
    raw = rng.normal(0.0, 1.0, (2000, 1, 6)) * np.array([1, 1, 1, 20, 20, 20])
    broadcast = [np.broadcast_to(a, (len(raw),) + a.shape[1:]) for a in (qpos0, qvel0, qpos1, qvel1)]
    qpos, qvel = correction.corrected(bodies, *broadcast, raw, contact_margin=0.01)
    placed = world_vertices(qpos1[:, 0], bodies.vertices[0])[0]
    contacts = placed[:, 2] < 0.01
    offsets = placed[contacts] - qpos1[0, 0, :3]
    omega = rotations.rotate(qpos[:, 0, 3:], qvel[:, 0, 3:])
    vertical = qvel[:, 0, None, 2] + np.cross(omega[:, None, :], offsets)[..., 2]
    assert contacts.sum() == 4 and (vertical >= -1e-12).all()  # MuJoCo had them at rest vertically
    energy = correction.kinetic_energy(bodies, qpos, qvel)
    limit = correction.kinetic_energy(bodies, qpos0, qvel0)
    assert (energy <= limit * (1 + 1e-9)).all()
    # A push into the floor is refused whole; slowing the slide is passed on unchanged.
    down, _ = correction.corrected(bodies, qpos0, qvel0, qpos1, qvel1, np.array([[[0, 0, -1.0, 0, 0, 0]]]), 0.01)
    assert np.allclose(down, qpos1)
    slower, slower_velocity = correction.corrected(
        bodies, qpos0, qvel0, qpos1, qvel1, np.array([[[-0.3, 0, 0, 0, 0, 0]]]), 0.01
    )
    assert np.isclose(slower_velocity[0, 0, 0], qvel1[0, 0, 0] - 0.3)
    assert np.isclose(slower[0, 0, 0], qpos1[0, 0, 0] - 0.3 * bodies.dt)


def test_without_a_correction_the_rollout_is_the_identified_mujoco(real_cube):
    context = make_context(real_cube.split("val").select(range(12)), real_cube.dt, 6)
    alone = ResidualContactModel(PARAMETERS, None, contact_margin=0.01).rollout(real_cube, context)
    mujoco = rollout_context(real_cube, context, PARAMETERS)
    # Step by step MuJoCo's solver starts cold; a whole rollout warm-starts it: micrometres apart over a toss.
    assert np.nanmax(np.abs(alone[..., :3] - mujoco[..., :3])) < 1e-4


def test_neighbour_features_point_at_the_nearest_other_body():
    dataset = falling_cubes(n_trajectories=2, n_frames=4, n_bodies=3)
    bodies = Bodies.of(dataset)
    qpos = dataset.split("train").poses[:, 0]
    qvel = body_frame_velocities(qpos, dataset.split("train").velocities[:, 0])
    features = correction.features(bodies, qpos, qvel, qpos, qvel)
    assert features.shape == (2, 3, bodies.n_features) and np.isfinite(features).all()
    position = qpos[..., :3]
    distance = np.linalg.norm(position[:, :, None] - position[:, None], axis=-1) + np.eye(3) * 1e9
    nearest = distance.argmin(-1)
    expected = rotations.rotate(
        rotations.conjugate(qpos[..., 3:]), np.take_along_axis(position, nearest[..., None], 1) - position
    )
    assert np.allclose(features[..., -7:-4], expected)
    assert np.allclose(features[..., -1], distance.min(-1))


def rising_cubes():
    """Cubes thrown upwards (free flight, so MuJoCo's linearisation is exact), recorded with a drift the correction
    should learn to follow: the rollout's loss then has a non-zero gradient."""
    dataset = falling_cubes(n_trajectories=30, n_frames=8, seed=3)
    split = dataset.split("train")
    rising = np.nonzero(split.velocities[:, 6, 0, 2] > 0.05)[0]  # up all through a 5-frame window
    split = split.select(rising)
    drift = np.arange(split.poses.shape[1])[None, :, None] * np.array([0.002, -0.001, 0.0005])
    split.poses[..., :3] += drift[:, :, None]
    split.poses[..., 3:] = rotations.multiply(
        rotations.from_rotation_vector(np.arange(8)[None, :, None, None] * np.array([0.0, 0.004, 0.0])),
        split.poses[..., 3:],
    )
    return dataclasses.replace(dataset, splits={"train": split, "val": split}), len(rising)


def test_the_rollout_gradient_is_the_loss_slope_in_free_flight():
    dataset, n = rising_cubes()
    assert n >= 3
    module = ResidualModule(dataset, context_frames=2, sysid={}, hidden=(8,), unroll=5)
    module.parameters_vector.copy_(torch.as_tensor([0.2, 0.2, 2000.0, 40.0], dtype=torch.float64))
    module.feature_std.fill_(1.0)
    windows = torch.as_tensor([[i, 0] for i in range(n)])
    bias = module.network[-1].bias
    loss = module.rollout_loss("train", windows)
    (gradient,) = torch.autograd.grad(loss, bias)
    step = 1e-4
    slopes = []
    for i in range(6):
        values = []
        for sign in (1, -1):
            with torch.no_grad():
                bias[i] += sign * step
                values.append(float(module.rollout_loss("train", windows)))
                bias[i] -= sign * step
        slopes.append((values[0] - values[1]) / (2 * step))
    assert np.abs(slopes).max() > 1e-3
    assert np.allclose(gradient.numpy(), slopes, rtol=0.05, atol=1e-3 * np.abs(slopes).max())


def test_residual_trains_on_the_real_cube_and_evaluate_scores_it_identically(tmp_path):
    overrides = ["dataset=contactnets_cube", "model=residual", "budget=smoke"]
    run_dir = tmp_path / "run"
    runs.train(compose_config("train", [*overrides, "test=true"], tmp_path), run_dir)
    fitted = json.loads((run_dir / "fitted.json").read_text())
    assert set(fitted["parameters"]) == {"object_friction_0", "floor_friction", "floor_stiffness", "floor_damping"}
    assert isinstance(fitted["correction_used"], bool)
    assert fitted["correction_used"] == (fitted["val_pos_err_corrected"] < fitted["val_pos_err_sysid"])
    document = runs.evaluate(
        compose_config("evaluate", [*overrides, f"train_dir={run_dir}", "split=test"], tmp_path), tmp_path / "eval"
    )
    trained = json.loads((run_dir / "test" / "metrics.json").read_text())
    assert document["pos_err"] == trained["pos_err"] and document["rot_err_rad"] == trained["rot_err_rad"]
