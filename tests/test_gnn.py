"""The mesh GNN: graphs, shape matching, features and targets, train-only statistics, training, checkpoints,
rollouts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from conftest import falling_cubes
from pytorch_lightning.callbacks import ModelCheckpoint

from contactbench import rotations
from contactbench.config import REPO_ROOT
from contactbench.kinematics import world_vertices
from contactbench.models.gnn.graph import MeshScene, build_edges, collision_radius
from contactbench.models.gnn.module import GNNDataModule, GNNModule, VertexWindows
from contactbench.models.gnn.network import InteractionLayer
from contactbench.models.gnn.shape_matching import fit_rigid_transform, poses_from_vertices, project_to_rigid
from contactbench.models.gnn.simulator import GNNContactModel, LearnedSimulator, random_walk_noise
from contactbench.models.selection import ValRollouts, rollout_errors
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.scene import Recordings, Split

TINY = {"latent_size": 16, "message_passing_steps": 2}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def without_spin(recordings: Recordings) -> Recordings:
    """The same free-fall positions with every body keeping its first orientation."""
    splits = {}
    for name, split in recordings.splits.items():
        poses, velocities = split.poses.copy(), split.velocities.copy()
        poses[..., 3:] = poses[:, :1, :, 3:]
        velocities[..., 3:] = 0.0
        splits[name] = Split(poses, split.lengths, velocities, split.extras)
    return dataclasses.replace(recordings, splits=splits)


def simulator_for(recordings: Recordings, **options) -> LearnedSimulator:
    scene = MeshScene.of(recordings)
    return LearnedSimulator(
        scene, recordings.dt, recordings.floor_z, collision_radius(scene.widths), **{**TINY, **options}
    )


# ---------------------------------------------------------------- graphs


def test_mesh_edges_cover_every_cube_edge_in_both_directions():
    scene = MeshScene.of(falling_cubes(n_bodies=2))
    assert scene.n_nodes == 16 and scene.n_bodies == 2
    # a triangulated cube: 12 box edges + 6 face diagonals, each both ways, per body
    assert scene.mesh_edges.shape == (2, 2 * 2 * 18)
    pairs = {tuple(edge) for edge in scene.mesh_edges.T}
    assert all((receiver, sender) in pairs for sender, receiver in pairs)
    assert np.all(scene.node_body[scene.mesh_edges[0]] == scene.node_body[scene.mesh_edges[1]])


def test_collision_edges_join_nearby_vertices_of_different_bodies_only():
    recordings = falling_cubes(n_bodies=3)
    scene = MeshScene.of(recordings)
    width = scene.widths[0]
    radius = collision_radius(scene.widths)
    identity = [1.0, 0.0, 0.0, 0.0]
    # graph 0: body 1 faces body 0 across a gap of 0.05 widths, body 2 far away; graph 1: all far apart
    poses = np.array(
        [
            [[0, 0, 1, *identity], [1.05 * width, 0, 1, *identity], [5, 0, 1, *identity]],
            [[0, 0, 1, *identity], [2, 0, 1, *identity], [5, 0, 1, *identity]],
        ]
    )
    positions = torch.as_tensor(scene.world_vertices(poses))
    edge_index, n_mesh = build_edges(
        positions, torch.as_tensor(scene.node_body), torch.as_tensor(scene.mesh_edges), radius
    )
    assert n_mesh == 2 * scene.mesh_edges.shape[1]
    senders, receivers = edge_index[:, n_mesh:].numpy()
    # the 4 facing corner pairs, 0.05 w apart; every other cross-body pair is over 1.0 w > 0.8 w apart
    assert len(senders) == 8
    pairs = set(zip(senders, receivers))
    assert all((r, s) in pairs for s, r in pairs)
    flat = positions.reshape(-1, 3).numpy()
    body = np.tile(scene.node_body, 2)
    assert np.all(body[senders] != body[receivers])
    assert np.all(np.linalg.norm(flat[senders] - flat[receivers], axis=1) < radius)
    assert set(body[senders]) == {0, 1} and np.all(senders < scene.n_nodes)
    np.testing.assert_allclose(np.linalg.norm(flat[senders] - flat[receivers], axis=1), 0.05 * width, rtol=1e-9)


def test_message_passing_is_an_interaction_network_summing_at_receivers():
    torch.manual_seed(0)
    layer = InteractionLayer(latent_size=8, hidden_layers=2)
    nodes, edges = torch.randn(5, 8), torch.randn(7, 8)
    edge_index = torch.tensor([[0, 1, 2, 3, 4, 4, 1], [1, 2, 0, 0, 0, 3, 2]])
    new_nodes, new_edges = layer(nodes, edge_index, edges)
    # the split first layer is one linear map of the concatenation [edge, sender, receiver]
    weight = torch.cat([layer.edge_input.weight, layer.sender_input.weight, layer.receiver_input.weight], dim=1)
    inputs = torch.cat([edges, nodes[edge_index[0]], nodes[edge_index[1]]], dim=-1)
    edge_updates = layer.edge_mlp(inputs @ weight.T + layer.edge_input.bias)
    torch.testing.assert_close(new_edges, edges + edge_updates)
    incoming = torch.zeros(5, 8).index_add_(0, edge_index[1], edge_updates)
    assert torch.all(incoming[4] == 0)  # node 4 only sends
    torch.testing.assert_close(new_nodes, nodes + layer.node_mlp(torch.cat([nodes, incoming], dim=-1)))


# ---------------------------------------------------------------- shape matching


def random_poses(rng, count):
    return np.concatenate([rng.uniform(-1, 1, (count, 3)), rotations.uniform_random(rng, count)], axis=-1)


def test_shape_matching_recovers_known_rigid_motions_exactly():
    rng = np.random.default_rng(1)
    rest = rng.normal(size=(10, 3)) + np.array([0.3, -0.2, 0.1])  # mesh frame origin away from the centroid
    poses = random_poses(rng, 20)
    fitted = poses_from_vertices(rest, [slice(0, 10)], world_vertices(poses, rest))[:, 0]
    np.testing.assert_allclose(fitted[:, :3], poses[:, :3], atol=1e-12)
    assert np.all(rotations.angle_between(fitted[:, 3:], poses[:, 3:]) < 1e-7)
    np.testing.assert_allclose(np.linalg.norm(fitted[:, 3:], axis=-1), 1.0, atol=1e-12)
    assert np.all(fitted[:, 3] >= 0)  # w first, non-negative


def test_shape_matching_is_the_least_squares_fit_of_noisy_vertices():
    rng = np.random.default_rng(2)
    rest = torch.as_tensor(rng.normal(size=(8, 3)))
    poses = random_poses(rng, 5)
    noisy = torch.as_tensor(world_vertices(poses, rest.numpy()) + rng.normal(scale=0.01, size=(5, 8, 3)))
    rotation, translation = fit_rigid_transform(rest, noisy)
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(5, dtype=torch.float64))

    def residual(rotation, translation):
        return ((rest @ rotation.transpose(-1, -2) + translation[:, None] - noisy) ** 2).sum(dim=(-1, -2))

    best = residual(rotation, translation)
    true_rotation = torch.as_tensor(rotations.to_matrix(poses[:, 3:]))
    assert torch.all(best <= residual(true_rotation, torch.as_tensor(poses[:, :3])))
    for _ in range(20):  # any small rigid perturbation of the fit fits worse
        turn = torch.as_tensor(rotations.to_matrix(rotations.from_rotation_vector(rng.normal(scale=1e-3, size=(5, 3)))))
        assert torch.all(
            residual(turn @ rotation, translation + torch.as_tensor(rng.normal(scale=1e-4, size=(5, 3)))) > best
        )
    np.testing.assert_allclose(translation.numpy(), poses[:, :3], atol=0.05)


def test_mirrored_vertices_still_give_a_proper_rotation():
    rest = torch.as_tensor(np.random.default_rng(3).normal(size=(8, 3)))
    rotation, _ = fit_rigid_transform(rest, rest * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    assert torch.isclose(torch.linalg.det(rotation), torch.tensor(1.0, dtype=torch.float64))


# ---------------------------------------------------------------- features, targets, noise, statistics


def test_free_fall_features_and_targets_are_velocity_and_gravity():
    recordings = without_spin(falling_cubes(n_trajectories=2, n_frames=12))
    simulator = simulator_for(recordings)  # unfitted: mean 0, std 1, so features are in physical units
    split = recordings.split("train")
    window = torch.as_tensor(simulator.scene.world_vertices(split.poses[:, :7]))
    gravity = torch.as_tensor(recordings.gravity)
    torch.testing.assert_close(simulator.acceleration_targets(window), gravity.expand(2, 8, 3), atol=1e-9, rtol=0)
    features = simulator.node_features(window[:, :6]).reshape(2, 8, 16)
    # semi-implicit Euler: x_t - x_{t-1} = dt v_t, so the finite differences are the stored velocities
    expected_velocities = torch.as_tensor(split.velocities[:, 1:6, 0, :3])
    torch.testing.assert_close(features[:, :, :15].reshape(2, 8, 5, 3), expected_velocities[:, None].expand(2, 8, 5, 3))
    height = (window[:, 5, :, 2] - recordings.floor_z).clamp(max=simulator.radius) / simulator.radius
    torch.testing.assert_close(features[:, :, 15], height)
    assert torch.all(features[:, :, 15] == 1.0)  # a metre up, well beyond the radius: clipped


def test_spinning_vertices_accelerate_towards_the_axis():
    recordings = without_spin(falling_cubes(n_trajectories=1, n_frames=8))
    omega, dt = 3.0, recordings.dt
    poses = recordings.split("train").poses.copy()
    poses[..., 3:] = rotations.from_rotation_vector(np.array([0, 0, omega]) * dt * np.arange(8)[:, None])[None, :, None]
    simulator = simulator_for(recordings)
    vertices = torch.as_tensor(simulator.scene.world_vertices(poses[:, :3]))
    acceleration = simulator.acceleration_targets(vertices)[0] - torch.as_tensor(recordings.gravity)
    offset = (vertices[0, 1] - torch.as_tensor(poses[0, 1, 0, :3]))[:, :2]
    centripetal = -offset * 2 * (1 - np.cos(omega * dt)) / dt**2  # exact for a discretely sampled circle
    torch.testing.assert_close(acceleration[:, :2], centripetal, atol=1e-9, rtol=1e-6)
    torch.testing.assert_close(acceleration[:, 2], torch.zeros(8, dtype=torch.float64), atol=1e-9, rtol=0)


def test_random_walk_noise_reaches_its_scale_at_the_last_step():
    torch.manual_seed(0)
    noise = random_walk_noise(torch.zeros(20000, 6, 1, 3), 3e-4)
    assert torch.all(noise[:, 0] == 0)
    last_step = noise[:, -1] - noise[:, -2]
    assert abs(last_step.std().item() - 3e-4) < 1e-5
    assert abs((noise[:, 1] - noise[:, 0]).std().item() - 3e-4 / 5**0.5) < 1e-5


def reference_statistics(split: Split, scene: MeshScene, dt: float) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    velocities, accelerations = [], []
    for n in range(split.n_trajectories):
        vertices = scene.world_vertices(split.poses[n, : split.lengths[n]])
        velocities.append(np.diff(vertices, axis=0).reshape(-1, 3) / dt)
        accelerations.append(np.diff(vertices, n=2, axis=0).reshape(-1, 3) / dt**2)
    return {
        name: (np.concatenate(v).mean(0), np.concatenate(v).std(0))
        for name, v in [("velocity", velocities), ("acceleration", accelerations)]
    }


def test_normalisation_comes_from_the_train_split_only():
    base = falling_cubes(n_trajectories=4, n_frames=14)
    train = base.split("train")
    lengths = np.array([14, 9, 11, 14])
    poses = train.poses.copy()
    poses[np.arange(14)[None, :] >= lengths[:, None]] = np.nan  # variable lengths, NaN after, as in real data
    train = Split(poses, lengths, None)
    fast = base.split("val")
    fast = Split(fast.poses * np.array([50, 50, 50, 1, 1, 1, 1]), fast.lengths, None)
    recordings = dataclasses.replace(base, splits={"train": train, "val": base.split("val")})
    other_val = dataclasses.replace(base, splits={"train": train, "val": fast})
    modules = []
    for dataset in (recordings, other_val):
        module = GNNModule(dataset, noise_std=0.0, **TINY)
        module.setup("fit")
        modules.append(module.simulator)
    reference = reference_statistics(train, modules[0].scene, base.dt)
    for name, (mean, std) in reference.items():
        for simulator in modules:
            np.testing.assert_allclose(getattr(simulator, f"{name}_mean").numpy(), mean, rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(getattr(simulator, f"{name}_std").numpy(), std, rtol=1e-5)
    noisy = GNNModule(recordings, noise_std=3e-4, **TINY)
    noisy.setup("fit")
    expected = np.sqrt(reference["velocity"][1] ** 2 + (3e-4 / base.dt) ** 2)
    np.testing.assert_allclose(noisy.simulator.velocity_std.numpy(), expected, rtol=1e-5)


# ---------------------------------------------------------------- rollouts


class ZeroNetwork(torch.nn.Module):
    def forward(self, node_features, edge_index, edge_features):
        return node_features.new_zeros(node_features.shape[0], 3)


@pytest.mark.parametrize("per_step_projection", [False, True])
def test_a_simulator_that_predicts_gravity_reproduces_free_fall(per_step_projection):
    recordings = without_spin(falling_cubes(n_trajectories=3, n_frames=30, n_bodies=2))
    simulator = simulator_for(recordings)
    simulator.network = ZeroNetwork()
    simulator.acceleration_mean.copy_(torch.as_tensor(recordings.gravity))
    simulator.normalisation_fitted.fill_(True)
    split = recordings.split("val")
    context = make_context(split, recordings.dt, 6)
    predicted = GNNContactModel(simulator, per_step_projection, batch_size=2).rollout(recordings, context)
    assert predicted.shape == (3, 30, 2, 7)
    np.testing.assert_array_equal(predicted[:, :6], split.poses[:, :6])
    np.testing.assert_allclose(predicted[..., :3], split.poses[..., :3], atol=2e-5)
    assert np.all(rotations.angle_between(predicted[..., 3:], split.poses[..., 3:]) < 1e-3)


def test_per_step_projection_keeps_every_body_rigid():
    recordings = falling_cubes(n_trajectories=2, n_frames=20, n_bodies=2)
    simulator = simulator_for(recordings)
    simulator.fit_normalisation(recordings.split("train"))
    context = torch.as_tensor(simulator.scene.world_vertices(recordings.split("val").poses[:, :6]), dtype=torch.float32)
    free = simulator.rollout(context, 10)
    projected = simulator.rollout(context, 10, per_step_projection=True)
    rest = simulator.rest_vertices
    for nodes in simulator.body_slices:
        rest_distances = torch.cdist(rest[nodes], rest[nodes])
        torch.testing.assert_close(
            torch.cdist(projected[..., nodes, :], projected[..., nodes, :]),
            rest_distances.expand(2, 10, 8, 8),
            atol=1e-5,
            rtol=0,
        )
        assert not torch.allclose(
            torch.cdist(free[..., nodes, :], free[..., nodes, :]), rest_distances.expand(2, 10, 8, 8), atol=1e-5
        )
    torch.testing.assert_close(project_to_rigid(rest, simulator.body_slices, projected), projected, atol=1e-5, rtol=0)


# ---------------------------------------------------------------- training and checkpoints


def test_training_steps_reduce_the_loss_on_a_fixed_batch():
    torch.manual_seed(0)
    recordings = falling_cubes(n_trajectories=4, n_frames=14)
    module = GNNModule(recordings, lr=1e-3, **TINY)
    module.setup("fit")
    batch = next(iter(GNNDataModule(recordings, batch_size=16).train_dataloader()))
    optimizer = module.configure_optimizers()
    before = module.simulator.loss(batch, add_noise=False).item()
    for _ in range(30):
        optimizer.zero_grad()
        module.simulator.loss(batch, add_noise=True).backward()
        optimizer.step()
    assert module.simulator.loss(batch, add_noise=False).item() < 0.5 * before


@pytest.mark.parametrize("n_bodies", [1, 3])
def test_trainer_checkpoints_reload_and_roll_out(tmp_path, n_bodies):
    pl.seed_everything(0)
    recordings = falling_cubes(n_trajectories=4, n_frames=16, n_bodies=n_bodies)
    module = GNNModule(recordings, context_frames=6, **TINY)
    checkpoint = ModelCheckpoint(dirpath=tmp_path, monitor="val/pos_err", mode="min", save_last=True)
    options = dict(
        val_check_interval=10,
        check_val_every_n_epoch=None,
        callbacks=[ValRollouts(trajectories=2), checkpoint],
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
    )
    trainer = pl.Trainer(max_steps=20, **options)
    trainer.fit(module, datamodule=GNNDataModule(recordings, context_frames=6))
    assert trainer.global_step == 20
    assert np.isfinite(trainer.callback_metrics["val/pos_err"].item())
    assert np.isfinite(trainer.callback_metrics["val/rot_err"].item())
    assert "val/one_step_loss" in trainer.callback_metrics
    best = GNNModule.load_from_checkpoint(checkpoint.best_model_path, dataset=recordings, weights_only=True)
    assert best.hparams.latent_size == 16 and bool(best.simulator.normalisation_fitted)
    torch.testing.assert_close(best.simulator.acceleration_std, module.simulator.acceleration_std)

    split = recordings.split("val")
    context = make_context(split, recordings.dt, 6)
    predicted = best.to_contact_model().rollout(recordings, context)
    assert predicted.shape == (4, 16, n_bodies, 7)
    np.testing.assert_array_equal(predicted[:, :6], split.poses[:, :6])
    np.testing.assert_allclose(np.linalg.norm(predicted[..., 3:], axis=-1), 1.0, atol=1e-9)
    assert np.all(np.isfinite(predicted))

    resumed = pl.Trainer(max_steps=24, **options)
    resumed.fit(
        GNNModule(recordings, context_frames=6, **TINY),
        datamodule=GNNDataModule(recordings),
        ckpt_path=checkpoint.last_model_path,
    )
    assert resumed.global_step == 24


def test_runs_on_the_real_cube_with_variable_lengths():
    real = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", splits=["train", "val"])
    small = dataclasses.replace(
        real, splits={"train": real.split("train").select(range(5)), "val": real.split("val").select(range(3))}
    )
    assert len(set(small.split("val").lengths)) > 1
    windows = VertexWindows(small.split("train"), MeshScene.of(small), 7)
    assert len(windows) == int(np.sum(small.split("train").lengths - 6))
    assert torch.all(torch.isfinite(windows[np.arange(len(windows))]))
    module = GNNModule(small, **TINY)
    module.setup("fit")
    assert module.simulator.floor_z == real.floor_z and module.simulator.radius == pytest.approx(0.8 * 0.1048)
    errors = rollout_errors(module.to_contact_model(), small, "val", 6, trajectories=3)
    assert np.isfinite(errors["pos_err"]) and errors["pos_err"] > 0
    context = make_context(small.split("val"), small.dt, 6)
    predicted = module.to_contact_model().rollout(small, context)
    assert predicted.shape == (3, int(small.split("val").lengths.max()), 1, 7)
    assert np.all(np.isfinite(predicted))


def test_an_untrained_module_or_another_scene_is_refused():
    recordings = falling_cubes()
    module = GNNModule(recordings, **TINY)
    with pytest.raises(RuntimeError, match="normalisation"):
        module.to_contact_model()
    module.setup("fit")
    two_cubes = falling_cubes(n_bodies=2)
    with pytest.raises(ValueError, match="other meshes"):
        module.to_contact_model().rollout(two_cubes, make_context(two_cubes.split("val"), two_cubes.dt, 6))
    with pytest.raises(ValueError, match="context frames"):
        GNNModule(recordings, context_frames=4)
