"""The rigid mesh GNN (model=gnn): torch quaternions, the rigid fit, exact free flight, rigidity, training, configs."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from conftest import falling_cubes
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from pytorch_lightning.callbacks import ModelCheckpoint, WeightAveraging
from torch.optim.swa_utils import get_ema_multi_avg_fn

from contactbench import metrics, rotations
from contactbench.config import CONFIG_DIR, REPO_ROOT
from contactbench.models.gnn import quaternions
from contactbench.models.gnn.graph import MeshScene, build_edges, collision_radius
from contactbench.models.gnn.module import GNNDataModule, GNNModule, inertia_per_mass
from contactbench.models.gnn.rigid import RigidGNNContactModel, RigidLearnedSimulator
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.scene import Split
from contactbench.tracking import ResumableCSVLogger, drop_rows_from_step

TINY = {"latent_size": 16, "message_passing_steps": 2}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def rigid_simulator(recordings, **options) -> RigidLearnedSimulator:
    scene = MeshScene.of(recordings)
    simulator = RigidLearnedSimulator(
        scene,
        recordings.dt,
        recordings.floor_z,
        recordings.gravity,
        collision_radius(scene.widths),
        0.25 * scene.widths.max(),
        **{**TINY, "velocity_history": 3, **options},
    )
    simulator.fit_normalisation(recordings.split("train"))
    return simulator


def test_torch_quaternions_match_the_numpy_ones():
    rng = np.random.default_rng(0)
    q0, q1 = rotations.uniform_random(rng, 50), rotations.uniform_random(rng, 50)
    vectors, rotation_vectors = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    t = torch.as_tensor
    np.testing.assert_allclose(quaternions.rotate(t(q0), t(vectors)).numpy(), rotations.rotate(q0, vectors), atol=1e-12)
    np.testing.assert_allclose(quaternions.multiply(t(q0), t(q1)).numpy(), rotations.multiply(q0, q1), atol=1e-12)
    np.testing.assert_allclose(
        quaternions.from_rotation_vector(t(rotation_vectors)).numpy(),
        rotations.from_rotation_vector(rotation_vectors),
        atol=1e-12,
    )
    np.testing.assert_allclose(
        quaternions.to_rotation_vector(t(q0)).numpy(), rotations.to_rotation_vector(q0), atol=1e-10
    )
    np.testing.assert_allclose(
        quaternions.angular_velocity(t(q0), t(q1), 0.01).numpy(),
        rotations.angular_velocity_from_quaternions(q0, q1, 0.01),
        atol=1e-8,
    )
    # exp and log are smooth through the identity (the free-flight case), gradients included
    tiny = torch.tensor([[1e-13, -2e-13, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    quaternions.to_rotation_vector(quaternions.from_rotation_vector(tiny)).sum().backward()
    assert torch.all(torch.isfinite(tiny.grad))


def test_the_rigid_fit_recovers_a_rigid_acceleration_field_exactly():
    recordings = falling_cubes(n_trajectories=2, n_bodies=2)
    simulator = rigid_simulator(recordings)
    poses = torch.as_tensor(recordings.split("train").poses[:, 5])
    vertices = simulator.bodies.vertices(poses)
    rng = np.random.default_rng(1)
    linear, angular = torch.as_tensor(rng.normal(size=(2, 2, 3))), torch.as_tensor(rng.normal(size=(2, 2, 3)))
    offsets = vertices - poses[:, simulator.node_body, :3]
    field = linear[:, simulator.node_body] + torch.linalg.cross(angular[:, simulator.node_body], offsets, dim=-1)
    fitted_linear, fitted_angular = simulator.bodies.rigid_fit(field, vertices, poses)
    torch.testing.assert_close(fitted_linear, linear, atol=1e-10, rtol=0)
    torch.testing.assert_close(fitted_angular, angular, atol=1e-10, rtol=0)
    # a field no rigid motion makes (squeezing a body) has no rigid part
    squeeze = -(vertices - simulator.bodies.per_body_sum(vertices)[:, simulator.node_body] / 8)
    for part in simulator.bodies.rigid_fit(squeeze, vertices, poses):
        torch.testing.assert_close(part, torch.zeros_like(part), atol=1e-10, rtol=0)


def test_with_solid_inertia_vertex_outputs_act_as_forces_on_the_solid_body():
    """Newton-Euler: one vertex of a cube (side w) pushed by f gives the centre of mass f / 8 and the body
    (r x f) / (8 I/m) with I/m = w^2 / 6, so a push at a corner turns the cube 3x faster than the least-squares fit."""
    recordings = falling_cubes(n_trajectories=1)
    inertia = inertia_per_mass(recordings, MeshScene.of(recordings))
    width = recordings.widths()[0]
    np.testing.assert_allclose(inertia[0], np.eye(3) * width**2 / 6, atol=1e-12)
    solid, least_squares = rigid_simulator(recordings, solid_inertia=inertia), rigid_simulator(recordings)
    poses = torch.as_tensor(recordings.split("train").poses[:, 5])
    vertices = solid.bodies.vertices(poses)
    push = torch.zeros_like(vertices)
    push[0, 0] = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    corner = vertices[0, 0] - poses[0, 0, :3]
    linear, angular = solid.bodies.rigid_fit(push, vertices, poses)
    torch.testing.assert_close(angular[0, 0], torch.linalg.cross(corner, push[0, 0], dim=-1) / (8 * width**2 / 6))
    torch.testing.assert_close(linear[0, 0], push[0, 0] / 8)  # the cube's vertex centroid is its centre of mass
    torch.testing.assert_close(least_squares.bodies.rigid_fit(push, vertices, poses)[1] * 3, angular)


def test_free_flight_is_exact_whatever_the_network_says():
    """Far from the floor and each other no vertex is gated in: spinning cubes fall exactly as the engine's scheme."""
    recordings = falling_cubes(n_trajectories=3, n_frames=20, n_bodies=2)  # 0.2 s: the lowest stays 10 cm up
    simulator = rigid_simulator(recordings)
    torch.nn.init.normal_(simulator.network.decoder[-1].bias, std=10.0)  # an untrained network that pushes hard
    split = recordings.split("val")
    predicted = RigidGNNContactModel(simulator, batch_size=2).rollout(recordings, make_context(split, recordings.dt, 6))
    np.testing.assert_array_equal(predicted[:, :6], split.poses[:, :6])
    np.testing.assert_allclose(predicted[..., :3], split.poses[..., :3], atol=1e-9)
    assert np.all(rotations.angle_between(predicted[..., 3:], split.poses[..., 3:]) < 1e-9)


def test_rollouts_in_contact_keep_every_body_rigid():
    """Bodies on the floor, pushed by an untrained network: pairwise vertex distances stay the rest ones (1e-6 m)."""
    recordings = falling_cubes(n_trajectories=2, n_frames=30, n_bodies=3)
    lowered = recordings.split("val").poses.copy()
    lowered[..., 2] -= lowered[:, :1, :, 2] - 0.06  # near the floor: every vertex gated in
    lowered[:, :, 1:, 0] = lowered[:, :, :1, 0] + 0.11 * np.arange(1, 3)  # and near each other: collision edges
    simulator = rigid_simulator(recordings)
    torch.nn.init.normal_(simulator.network.decoder[-1].bias, std=1.0)
    history = torch.as_tensor(lowered[:, :4])
    predicted = simulator.rollout(history, 20)
    assert not torch.allclose(predicted[..., :3], torch.as_tensor(lowered[:, 4:24, :, :3]), atol=1e-3)  # it did push
    vertices = simulator.bodies.vertices(predicted)
    rest = simulator.bodies.rest_vertices_double
    for nodes in simulator.body_slices:
        torch.testing.assert_close(
            torch.cdist(vertices[..., nodes, :], vertices[..., nodes, :]),
            torch.cdist(rest[nodes], rest[nodes]).expand(2, 20, 8, 8),
            atol=1e-6,
            rtol=0,
        )


def test_separation_pushes_overlapping_bodies_apart_and_leaves_the_rest_alone():
    """Three cubes, two of them turned and overlapping by up to 3 cm: afterwards the exact (separating-axis) depth is
    gone to 0.1 mm, orientations are untouched, and a third cube far away has not moved."""
    recordings = falling_cubes(n_trajectories=4, n_bodies=3)
    simulator = rigid_simulator(recordings, separate_bodies=True)
    rng = np.random.default_rng(3)
    poses = np.zeros((4, 3, 7))
    poses[..., 3:] = rotations.uniform_random(rng, 12).reshape(4, 3, 4)
    poses[:, 0, :3] = [0.0, 0.0, 0.3]
    poses[:, 1, :3] = poses[:, 0, :3] + rng.normal(size=(4, 3)) * 0.01 + [0.07, 0.0, 0.0]
    poses[:, 2, :3] = [1.0, 1.0, 0.3]
    meshes = [recordings.body_mesh(k) for k in range(3)]
    before = metrics.interbody_penetration(poses, meshes).max(axis=(-2, -1))
    assert np.all(before > 0.01)
    separated = simulator.bodies.separate(torch.as_tensor(poses)).numpy()
    assert np.all(metrics.interbody_penetration(separated, meshes).max(axis=(-2, -1)) < 1e-4)
    np.testing.assert_array_equal(separated[..., 3:], poses[..., 3:])
    np.testing.assert_array_equal(separated[:, 2], poses[:, 2])
    np.testing.assert_allclose(
        simulator.bodies.separate(torch.as_tensor(separated)).numpy(), separated, rtol=0, atol=1e-12
    )


def test_training_steps_reduce_the_loss_in_contact():
    torch.manual_seed(0)
    recordings = falling_cubes(n_trajectories=4, n_frames=14)
    lowered = recordings.split("train").poses.copy()
    lowered[..., 2] = 0.04 + 0.001 * np.arange(14)[None, :, None]  # sliding up a ramp near the floor: gated in
    module = GNNModule(recordings, lr=3e-3, rigid=True, velocity_history=3, **TINY)
    module.setup("fit")
    batch = torch.as_tensor(lowered[:, :5])
    before = module.simulator.loss(batch, add_noise=False).item()
    optimizer = module.configure_optimizers()
    for _ in range(60):
        optimizer.zero_grad()
        module.simulator.loss(batch, add_noise=True).backward()
        optimizer.step()
    assert module.simulator.loss(batch, add_noise=False).item() < 0.2 * before


def test_windows_are_float64_poses_and_batches_hold_a_vertex_budget():
    recordings = falling_cubes(n_trajectories=2, n_frames=14, n_bodies=2)
    datamodule = GNNDataModule(recordings, velocity_history=3, rigid=True, batch_vertices=80)
    assert datamodule.batch_size == 5  # 80 vertices = 5 scenes of two cubes
    batch = next(iter(datamodule.train_dataloader()))
    assert batch.shape == (5, 5, 2, 7) and batch.dtype == torch.float64


def compose_model(model: str, budget: str):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name="train", overrides=[f"model={model}", f"budget={budget}"])


def test_gnn_paper_composes_with_the_papers_values():
    cfg = compose_model("gnn_paper", "paper")
    module, datamodule = cfg.model.module, cfg.model.datamodule
    assert cfg.model.name == "gnn_paper" and module.rigid is False and module.per_step_projection is False
    assert (module.latent_size, module.message_passing_steps, module.lr, module.noise_std, module.velocity_history) == (
        128,
        10,
        1e-4,
        3e-4,
        5,
    )
    assert datamodule.batch_size == 64 and cfg.model.trainer.max_steps == 1_000_000
    assert cfg.model.callbacks.checkpoint.monitor == "val/pos_err"


@pytest.mark.parametrize("budget", ["smoke", "sensitivity", "quick", "paper"])
def test_gnn_is_the_rigid_model_at_every_budget(budget):
    cfg = compose_model("gnn", budget)
    assert cfg.model.module.rigid is True and cfg.model.datamodule.rigid is True
    assert cfg.model.module.velocity_history + 1 <= cfg.context_frames


def test_smoke_training_improves_on_the_untrained_model():
    """budget=smoke's settings on 40 real tosses: the held-out one-step loss falls below the untrained network's."""
    cfg = compose_model("gnn", "smoke")
    real = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", splits=["train", "val"])
    small = dataclasses.replace(
        real, splits={"train": real.split("train").select(range(40)), "val": real.split("val").select(range(10))}
    )
    pl.seed_everything(0)
    module = instantiate(cfg.model.module, _partial_=True)(dataset=small, context_frames=cfg.context_frames)
    datamodule = instantiate(cfg.model.datamodule, _partial_=True)(dataset=small, context_frames=cfg.context_frames)
    module.setup("fit")
    held_out = next(iter(datamodule.val_dataloader()))
    before = module.simulator.loss(held_out, add_noise=False).item()
    trainer = pl.Trainer(
        max_steps=cfg.model.trainer.max_steps,
        limit_val_batches=0,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.fit(module, datamodule=datamodule)
    assert trainer.global_step == cfg.model.budgets.smoke.max_steps
    assert module.simulator.loss(held_out, add_noise=False).item() < 0.9 * before


def test_collision_edges_carry_the_receivers_depth_inside_the_senders_body():
    recordings = falling_cubes(n_bodies=2)
    simulator = rigid_simulator(recordings)
    width = simulator.scene.widths[0]
    identity = [1.0, 0.0, 0.0, 0.0]
    # body 1 overlaps body 0 by 0.01 m along x, offset 0.02 m in y and z: one corner of it, at (0.04, -0.03, 0.97),
    # is 0.01 m inside body 0's face x = 0.05 and farther from every other face
    poses = torch.as_tensor([[[0, 0, 1, *identity], [width - 0.01, 0.02, 1.02, *identity]]], dtype=torch.float64)
    current = simulator.bodies.vertices(poses).float()
    edge_index, n_mesh = build_edges(current, simulator.node_body, simulator.mesh_edges, simulator.radius)
    features = simulator.edge_features(current, edge_index, n_mesh)
    assert features.shape == (edge_index.shape[1], 13)
    assert torch.all(features[:n_mesh, 9:] == 0)
    senders, receivers = edge_index[:, n_mesh:]
    corner = (current[0, receivers] - torch.tensor([0.04, -0.03, 0.97])).norm(dim=-1) < 1e-5
    inside = (simulator.node_body[senders] == 0) & corner
    assert int(inside.sum()) > 0
    torch.testing.assert_close(
        features[n_mesh:][inside, 9], torch.full((int(inside.sum()),), -0.01 / simulator.radius), atol=1e-5, rtol=0
    )
    torch.testing.assert_close(
        features[n_mesh:][inside, 10:], torch.tensor([1.0, 0.0, 0.0]).expand(int(inside.sum()), 3), atol=1e-5, rtol=0
    )


def test_free_flight_acceleration_is_measured_on_train_not_read_from_meta():
    """A tracker's time base shows as an apparent gravity: the data fall at 9.81 m/s² while meta.json says 10."""
    recordings = falling_cubes(n_trajectories=3, n_frames=20, n_bodies=2)
    mislabelled = dataclasses.replace(recordings, meta={**recordings.meta, "gravity": [0.0, 0.0, -10.0]})
    simulator = rigid_simulator(mislabelled)
    torch.testing.assert_close(
        simulator.free_flight_acceleration, torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64), atol=1e-8, rtol=0
    )
    near_floor = recordings.split("train").poses.copy()
    near_floor[..., 2] = 0.06  # every body within the contact distance of the floor: no frame is free
    assert not simulator.free_of_contact(torch.as_tensor(near_floor)).any()


def test_a_run_resumed_mid_epoch_trains_exactly_as_an_uninterrupted_one(tmp_path):
    """Batches and training noise come from (seed, step): resuming from a mid-epoch checkpoint changes no weight, nor
    the weights' moving average the run keeps."""
    recordings = falling_cubes(n_trajectories=6, n_frames=14)
    lowered = recordings.split("train").poses.copy()
    lowered[..., 2] = 0.04 + 0.001 * np.arange(14)[None, :, None]
    recordings = dataclasses.replace(
        recordings, splits={**recordings.splits, "train": Split(lowered, recordings.split("train").lengths)}
    )
    options = {"rigid": True, "velocity_history": 3, "lr": 1e-3, "lr_schedule": "cosine", "seed": 7, **TINY}
    data = {"rigid": True, "velocity_history": 3, "batch_size": 4, "seed": 7}  # 60 windows: 15 steps an epoch

    def fit(max_steps: int, resume_from: str | None = None, callbacks=()):
        pl.seed_everything(0)
        module = GNNModule(recordings, **options)
        trainer = pl.Trainer(
            max_steps=max_steps,
            limit_val_batches=0,
            logger=False,
            callbacks=[
                *callbacks,
                WeightAveraging(multi_avg_fn=get_ema_multi_avg_fn(0.9), use_buffers=False),
            ],  # as gnn.yaml
            enable_checkpointing=bool(callbacks),
            enable_progress_bar=False,
            enable_model_summary=False,
        )
        trainer.fit(module, datamodule=GNNDataModule(recordings, **data), ckpt_path=resume_from)
        return module

    class KilledAtStepFive(pl.Callback):  # the same run (max_steps, schedule), stopped once step 5 is checkpointed
        def on_train_batch_end(self, trainer, *args):
            trainer.should_stop = trainer.global_step >= 5

    checkpoint = ModelCheckpoint(dirpath=tmp_path, every_n_train_steps=5, save_top_k=-1, filename="{step}")
    fit(10, callbacks=[checkpoint, KilledAtStepFive()])
    pl.seed_everything(123)  # a resumed process starts from another global random state
    resumed = fit(10, resume_from=str(tmp_path / "step=5.ckpt"))
    uninterrupted = fit(10)
    for name, value in uninterrupted.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[name], value, atol=0, rtol=0, msg=name)


def test_the_csv_log_keeps_its_rows_across_a_resume(tmp_path):
    logger = ResumableCSVLogger(save_dir=tmp_path, name="csv", version="")
    logger.log_metrics({"train/loss": 1.0}, step=1)
    logger.log_metrics({"train/loss": 0.5}, step=2)
    logger.save()
    drop_rows_from_step(tmp_path, 2)  # resuming from step 2: that step is logged again
    again = ResumableCSVLogger(save_dir=tmp_path, name="csv", version="")
    again.log_metrics({"train/loss": 0.4, "val/pos_err": 0.3}, step=2)
    again.save()
    rows = list(csv.DictReader(open(tmp_path / "csv" / "metrics.csv")))
    assert [(row["step"], row["train/loss"]) for row in rows] == [("1", "1.0"), ("2", "0.4")]
    assert rows[1]["val/pos_err"] == "0.3"
