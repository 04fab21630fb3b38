"""Learned mesh simulator: graph features from a vertex position history, per-vertex acceleration out, rollouts.

Design choices (paper §4.3 after Sanchez-Gonzalez et al. 2020 and Allen et al. 2022):
- Input: every node's position at the last H + 1 frames, H = `velocity_history` = 5 (the paper's "five previous
  velocities"), so the protocol's 6 context frames are exactly enough; longer contexts use their last H + 1 frames.
- Node features (3H + 1): the H finite-difference velocities (x_t − x_{t−1}) / dt, oldest first, normalised per
  axis; the height above the floor z − floor_z, clipped above at the collision radius and divided by it. The floor is
  a boundary feature, not a set of nodes: a flat infinite floor has no vertices of its own, and a clipped distance
  tells each vertex how near it is as directly as an edge would. Negative heights (penetration; the real cube's
  tracked floor is 2 mm below z = 0) are kept, unclipped. No body-type or static flag: every body of the benchmark
  scenes is free, and the rest-shape edge features already tell meshes apart. Over terrain (a ramp, a step, a height
  field: ground.py) the height is the ground's signed distance, and the ground's normal there joins it (3 more).
- Edge features (9): sender − receiver displacement divided by the collision radius and its norm, in the current
  positions and in the rest shape (the rest part is zero for collision edges, which join different bodies), and a
  flag that is 1 on collision edges.
- Target: per-vertex acceleration (x_{t+1} − 2 x_t + x_{t−1}) / dt², normalised per axis; loss: MSE. The next
  positions are x_{t+1} = 2 x_t − x_{t−1} + a dt².
- Training noise: a random walk on the input velocities whose last step has standard deviation `noise_std` (m),
  integrated into the input positions (first frame noise-free); the target is shifted by the last input position's
  noise, so the model learns to cancel the velocity noise it sees. The paper's scale is 3e-4 (m here).
- Normalisation: per-axis mean and standard deviation of vertex velocities and accelerations over the valid frames
  of the train split only, with the training noise added in quadrature (as the reference implementation does);
  held in buffers, so checkpoints carry them.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from contactbench.ground import Ground
from contactbench.models.base import ContactModel
from contactbench.models.gnn.graph import MeshScene, build_edges
from contactbench.models.gnn.network import EncodeProcessDecode
from contactbench.models.gnn.shape_matching import poses_from_vertices, project_to_rigid
from contactbench.protocol import Context
from contactbench.scene import Scene, Split

EDGE_FEATURES = 9
# Floor on the normalisation scales (m/s, m/s²): a train split without motion along an axis would divide by zero.
MIN_STD = 1e-6
# Trajectories whose vertices are placed at once when computing normalisation statistics (bounds memory).
STATISTICS_CHUNK = 64


def random_walk_noise(positions: torch.Tensor, std: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Noise for positions [B, H + 1, n, 3]: velocity noise is a random walk reaching `std` at the last step."""
    steps = positions.shape[1] - 1
    draws = torch.randn(positions[:, 1:].shape, generator=generator, dtype=positions.dtype, device=positions.device)
    velocity_noise = torch.cumsum(draws * (std / steps**0.5), dim=1)
    return torch.cat([torch.zeros_like(positions[:, :1]), torch.cumsum(velocity_noise, dim=1)], dim=1)


class LearnedSimulator(nn.Module):
    """The graph network wrapped as a one-step simulator of a scene's mesh vertices."""

    extra_node_features = 0  # subclasses that add node or edge features say how many
    extra_edge_features = 0

    def __init__(
        self,
        scene: MeshScene,
        dt: float,
        floor_z: float,
        radius: float,
        velocity_history: int = 5,
        latent_size: int = 128,
        message_passing_steps: int = 10,
        hidden_layers: int = 2,
        noise_std: float = 3e-4,
        ground: Ground | None = None,
    ):
        super().__init__()
        self.scene = scene
        self.body_slices = scene.body_slices()
        self.dt = dt
        self.ground = Ground(float(floor_z), [], [], []) if ground is None else ground
        self.floor_z = self.ground.floor_z
        # Over terrain a vertex also needs the way out of the ground (its normal): three more node features.
        self.ground_normal_features = 0 if self.ground.flat else 3
        self.radius = radius
        self.velocity_history = velocity_history
        self.noise_std = noise_std
        rest = torch.as_tensor(scene.rest_vertices, dtype=torch.float32)
        senders, receivers = scene.mesh_edges
        # Scene geometry comes from the dataset each time the model is built, so checkpoints need not carry it.
        self.register_buffer("rest_vertices", rest, persistent=False)
        self.register_buffer("node_body", torch.as_tensor(scene.node_body), persistent=False)
        self.register_buffer("mesh_edges", torch.as_tensor(scene.mesh_edges), persistent=False)
        self.register_buffer("rest_displacements", (rest[senders] - rest[receivers]) / radius, persistent=False)
        self.register_buffer("velocity_mean", torch.zeros(3))
        self.register_buffer("velocity_std", torch.ones(3))
        self.register_buffer("acceleration_mean", torch.zeros(3))
        self.register_buffer("acceleration_std", torch.ones(3))
        self.register_buffer("normalisation_fitted", torch.tensor(False))
        self.network = EncodeProcessDecode(
            node_input_size=3 * velocity_history + 1 + self.ground_normal_features + self.extra_node_features,
            edge_input_size=EDGE_FEATURES + self.extra_edge_features,
            output_size=3,
            latent_size=latent_size,
            message_passing_steps=message_passing_steps,
            hidden_layers=hidden_layers,
        )

    # ------------------------------------------------------------ normalisation

    def fit_normalisation(self, split: Split) -> None:
        """Velocity and acceleration statistics of every vertex over the valid frames of `split` (pass train only)."""
        names = ("velocity", "acceleration")
        sums = {name: np.zeros((2, 3)) for name in names}
        counts = dict.fromkeys(names, 0)
        for start in range(0, split.n_trajectories, STATISTICS_CHUNK):
            part = split.select(np.arange(start, min(start + STATISTICS_CHUNK, split.n_trajectories)))
            vertices = self.scene.world_vertices(part.poses)  # [c, T, n, 3], NaN after lengths
            frames = np.arange(part.n_frames)
            differences = {
                "velocity": (np.diff(vertices, axis=1) / self.dt, frames[:-1] + 1),
                "acceleration": (np.diff(vertices, n=2, axis=1) / self.dt**2, frames[:-2] + 2),
            }
            for name, (values, last_frame) in differences.items():
                inside = values[last_frame[None, :] < part.lengths[:, None]]  # [M, n, 3]
                sums[name] += [inside.sum(axis=(0, 1)), np.square(inside).sum(axis=(0, 1))]
                counts[name] += inside.shape[0] * inside.shape[1]
        if counts["acceleration"] == 0:
            raise ValueError("the train split has no three consecutive valid frames to estimate accelerations from")
        noise_scale = {"velocity": self.noise_std / self.dt, "acceleration": self.noise_std / self.dt**2}
        for name in names:
            mean = sums[name][0] / counts[name]
            variance = np.maximum(sums[name][1] / counts[name] - mean**2, 0.0)
            std = np.maximum(np.sqrt(variance + noise_scale[name] ** 2), MIN_STD)
            getattr(self, f"{name}_mean").copy_(torch.as_tensor(mean))
            getattr(self, f"{name}_std").copy_(torch.as_tensor(std))
        self.normalisation_fitted.fill_(True)

    # ------------------------------------------------------------ features and one step

    def clearance(self, points: torch.Tensor) -> torch.Tensor:
        """The ground's signed distance [...] at points [..., 3]: the height above the floor on flat scenes."""
        if self.ground.flat:
            return points[..., 2] - self.floor_z
        return self.ground.distance(points)[0]

    def node_features(self, positions: torch.Tensor) -> torch.Tensor:
        """positions [B, H + 1, n, 3] -> [B * n, 3H + 1] (and the ground's normal, 3 more, over terrain)."""
        velocities = (torch.diff(positions, dim=1) / self.dt - self.velocity_mean) / self.velocity_std
        history = velocities.permute(0, 2, 1, 3).flatten(2)
        if self.ground.flat:
            height = (positions[:, -1, :, 2:] - self.floor_z).clamp(max=self.radius) / self.radius
            return torch.cat([history, height], dim=-1).flatten(0, 1)
        distance, normal = self.ground.distance(positions[:, -1])
        height = distance[..., None].clamp(max=self.radius) / self.radius
        return torch.cat([history, height, normal], dim=-1).flatten(0, 1)

    def edge_features(self, current: torch.Tensor, edge_index: torch.Tensor, n_mesh_edges: int) -> torch.Tensor:
        """current positions [B, n, 3], edge index of the stacked graphs (mesh edges first) -> [E, 9]."""
        flat = current.flatten(0, 1)
        senders, receivers = edge_index
        displacement = (flat[senders] - flat[receivers]) / self.radius
        n_collision = edge_index.shape[1] - n_mesh_edges
        rest = torch.cat([self.rest_displacements.repeat(current.shape[0], 1), displacement.new_zeros(n_collision, 3)])
        is_collision = torch.cat([displacement.new_zeros(n_mesh_edges, 1), displacement.new_ones(n_collision, 1)])
        return torch.cat(
            [
                displacement,
                torch.linalg.vector_norm(displacement, dim=-1, keepdim=True),
                rest,
                torch.linalg.vector_norm(rest, dim=-1, keepdim=True),
                is_collision,
            ],
            dim=-1,
        )

    def forward(self, positions: torch.Tensor) -> torch.Tensor:
        """Normalised per-vertex accelerations [B, n, 3] predicted from positions [B, H + 1, n, 3]."""
        current = positions[:, -1]
        edge_index, n_mesh_edges = build_edges(current, self.node_body, self.mesh_edges, self.radius)
        output = self.network(
            self.node_features(positions), edge_index, self.edge_features(current, edge_index, n_mesh_edges)
        )
        return output.reshape(current.shape)

    def acceleration_targets(self, window: torch.Tensor) -> torch.Tensor:
        """Normalised accelerations [B, n, 3] of the last three frames of window [B, ≥3, n, 3]."""
        acceleration = (window[:, -1] - 2 * window[:, -2] + window[:, -3]) / self.dt**2
        return (acceleration - self.acceleration_mean) / self.acceleration_std

    def loss(self, window: torch.Tensor, add_noise: bool, generator: torch.Generator | None = None) -> torch.Tensor:
        """MSE on normalised accelerations for windows [B, H + 2, n, 3] (inputs, then the next frame)."""
        inputs = window[:, :-1]
        next_positions = window[:, -1]
        if add_noise and self.noise_std > 0:
            noise = random_walk_noise(inputs, self.noise_std, generator)
            inputs = inputs + noise
            next_positions = next_positions + noise[:, -1]
        targets = self.acceleration_targets(torch.cat([inputs[:, -2:], next_positions[:, None]], dim=1))
        return F.mse_loss(self(inputs), targets)

    def next_positions(self, positions: torch.Tensor) -> torch.Tensor:
        """Positions [B, n, 3] one frame after positions [B, H + 1, n, 3]."""
        acceleration = self(positions) * self.acceleration_std + self.acceleration_mean
        return 2 * positions[:, -1] - positions[:, -2] + acceleration * self.dt**2

    @torch.no_grad()
    def rollout(self, context: torch.Tensor, n_steps: int, per_step_projection: bool = False) -> torch.Tensor:
        """Autoregressive prediction of the n_steps frames [B, n_steps, n, 3] after context positions [B, C, n, 3]."""
        history = context[:, -(self.velocity_history + 1) :]
        predicted = []
        for _ in range(n_steps):
            positions = self.next_positions(history)
            if per_step_projection:
                positions = project_to_rigid(self.rest_vertices, self.body_slices, positions)
            predicted.append(positions)
            history = torch.cat([history[:, 1:], positions[:, None]], dim=1)
        return torch.stack(predicted, dim=1) if predicted else context[:, :0]


def check_same_scene(simulator: LearnedSimulator, dataset: Scene, context: Context) -> None:
    """Refuse a dataset whose meshes differ from the training scene's, or a context too short for the history."""
    scene = simulator.scene
    given = MeshScene.of(dataset)
    if (
        given.n_nodes != scene.n_nodes
        or not np.array_equal(given.mesh_edges, scene.mesh_edges)
        or not np.allclose(given.rest_vertices, scene.rest_vertices)
    ):
        raise ValueError(f"dataset {dataset.name!r} has other meshes than the scene this GNN was trained on")
    if context.n_context < simulator.velocity_history + 1:
        raise ValueError(f"the GNN needs {simulator.velocity_history + 1} context frames, got {context.n_context}")


class GNNContactModel(ContactModel):
    """A trained simulator as a contact model: vertex rollout from the context, then shape matching to poses."""

    name = "gnn_paper"

    def __init__(self, simulator: LearnedSimulator, per_step_projection: bool = False, batch_size: int = 256):
        self.simulator = simulator
        self.per_step_projection = per_step_projection
        self.batch_size = batch_size

    def rollout(self, scene: Scene, context: Context) -> np.ndarray:
        check_same_scene(self.simulator, scene, context)
        scene = self.simulator.scene
        n_steps = context.horizon - context.n_context
        vertices = scene.world_vertices(context.poses)
        device = self.simulator.rest_vertices.device
        predicted = np.concatenate(
            [
                self.simulator.rollout(
                    torch.as_tensor(vertices[start : start + self.batch_size], dtype=torch.float32, device=device),
                    n_steps,
                    self.per_step_projection,
                )
                .cpu()
                .numpy()
                for start in range(0, len(vertices), self.batch_size)
            ]
        )
        poses = poses_from_vertices(scene.rest_vertices, scene.body_slices(), predicted)
        return np.concatenate([context.poses, poses], axis=1)
