"""Rigid mesh GNN: per-vertex outputs projected onto one rigid acceleration per body, integrated as rigid bodies.

The paper's GNN (simulator.py) moves every vertex on its own and restores rigidity once, after the rollout. Here
rigidity holds at every step by construction, as Allen et al. (2022) obtain with shape matching inside the loop:
- The graph, features and network are the paper's (vertices as nodes, mesh and collision edges, clipped floor height,
  a history of finite-difference vertex velocities).
- The network's per-vertex outputs f_i are *contact* accelerations; each body's rigid acceleration is their least-
  squares rigid fit about the vertex centroid c: linear a = mean f_i, angular α = J⁻¹ Σ r_i × f_i with
  J = Σ (|r_i|² I − r_i r_iᵀ), r_i = x_i − c (shape matching linearised to accelerations, so it is linear and
  differentiable, with none of the SVD's degenerate gradients for cubes). The centre of mass then accelerates by
  a − α × (c − x_com).
  With solid_inertia (model=gnn's default) J is instead n times the body's own inertia per unit mass about c: the
  outputs act as forces on the solid body, so a push at one vertex turns a cube as a blow there would, three times
  as fast as the least-squares fit has it (Newton–Euler, exactly where the vertex centroid is the centre of mass,
  as for every benchmark solid and the real cube). It helps on PyBullet-made tosses and hurts on the real cube,
  whose impacts and tracking are not PyBullet's (measured: docs/results/matrix.md).
- Contact gate: a vertex contributes only when it is within `contact_distance` of the floor or has a collision edge
  to another body; with floor_gate (the default) only when within floor_gate of the floor now or at the next
  frame in free flight, so nothing acts on a body a step or more before it lands. Far from everything a body
  follows gravity exactly, with constant velocity and spin: the network spends nothing on free flight, and free
  flight drifts nowhere. (Every benchmark solid has an isotropic inertia, so torque-free spin is constant.)
- Gravity is what the train split shows: the mean acceleration of bodies in free flight (no vertex gated in), in
  place of meta.gravity, so a tracker's time base or length scale (an apparent gravity) is measured, not hard-wired.
  The real cube falls at 9.59 m/s², not the 9.81 its meta.json states. Without free-flight frames: meta.gravity.
- Semi-implicit Euler on poses, the engines' own scheme: v_{t+1} = v_t + a dt, x_{t+1} = x_t + v_{t+1} dt,
  q_{t+1} = exp(ω_{t+1} dt) ⊗ q_t, with v_t, ω_t backward differences of the last two poses, so exact
  accelerations reproduce recorded PyBullet frames exactly. Training targets are the same accelerations computed
  from recorded poses, compared as the vertex accelerations they imply (a + α × r_i), normalised per axis.
- Bodies apart (separate_bodies): after every rollout step, overlapping bodies are pushed apart by their exact
  penetration depth (separating-axis test), a position projection as in position-based dynamics. The one-step loss
  cannot teach non-penetration of stacked bodies well enough: without it three cubes end 12 mm inside each other.
- Joints (the articulated elbow): the network's outputs are contact alone; each hinge's reaction and its recorded
  damping enter the rigid accelerations by Newton-Euler (`jointed`: the least-kinetic-energy impulse that keeps the
  anchors together and the axes turning as one over the step), so a link swings on its neighbour as the multibody
  does (in the air, 1e-6 m of PyBullet's elbow a step), in training as in rollouts. keep_joints closes what the
  linearised step leaves; jointed links are not pushed apart by translation (it would only fight the hinge).
- Training noise: the paper's random walk on the input positions, and its rotational twin on orientations with a
  last-step scale of noise_std / half-width (the same displacement at a corner); the target frame is shifted by the
  last input frame's noise, so the model learns to cancel velocity noise.
"""

from __future__ import annotations

import numpy as np
import torch

from contactbench.models.base import ContactModel
from contactbench.models.gnn import quaternions
from contactbench.models.gnn.dynamics import RigidBodies
from contactbench.models.gnn.graph import MeshScene, build_edges
from contactbench.models.gnn.simulator import STATISTICS_CHUNK, LearnedSimulator, check_same_scene, random_walk_noise
from contactbench.protocol import Context
from contactbench.scene import Joint, Scene, Split


class RigidLearnedSimulator(LearnedSimulator):
    """The paper's graph network, its per-vertex outputs turned into rigid-body accelerations and integrated."""

    extra_node_features = 2
    extra_edge_features = 4

    def __init__(
        self,
        scene: MeshScene,
        dt: float,
        floor_z: float,
        gravity: np.ndarray,
        radius: float,
        contact_distance: float,
        separate_bodies: bool = False,
        floor_gate: float | None = None,
        solid_inertia: np.ndarray | None = None,
        joints: tuple[Joint, ...] = (),
        masses: np.ndarray | None = None,
        **options,
    ):
        self.contact_distance = contact_distance
        self.floor_gate = floor_gate
        super().__init__(scene, dt, floor_z, radius, **options)
        self.bodies = RigidBodies(scene, dt, separate_bodies, solid_inertia, joints, masses)
        self.register_buffer("scene_gravity", torch.as_tensor(np.asarray(gravity, dtype=np.float64)), persistent=False)
        self.register_buffer("half_widths", torch.as_tensor(scene.widths / 2, dtype=torch.float64), persistent=False)
        # the acceleration of bodies in free flight, measured on the train split (fit_normalisation); meta's until then
        self.register_buffer("free_flight_acceleration", torch.as_tensor(np.asarray(gravity, dtype=np.float64)))
        self.register_buffer("faces", torch.as_tensor(scene.faces), persistent=False)
        self.register_buffer("face_body", torch.as_tensor(scene.node_body[scene.faces[:, 0]]), persistent=False)

    def fit_normalisation(self, split: Split) -> None:
        """The paper's statistics, and the free-flight acceleration: the mean second difference of the centre of mass
        over the frames where no vertex of the body is gated in (pass train only)."""
        super().fit_normalisation(split)
        total, count = np.zeros(3), 0
        for start in range(0, split.n_trajectories, STATISTICS_CHUNK):
            part = split.select(np.arange(start, min(start + STATISTICS_CHUNK, split.n_trajectories)))
            free = self.free_of_contact(torch.as_tensor(part.poses)).numpy()[:, 1:-1]  # [c, T - 2, K]
            positions = part.poses[..., :3]
            acceleration = (positions[:, 2:] - 2 * positions[:, 1:-1] + positions[:, :-2]) / self.dt**2
            inside = free & (np.arange(1, part.n_frames - 1)[None, :, None] + 1 < part.lengths[:, None, None])
            total += acceleration[inside].sum(axis=0)
            count += int(inside.sum())
        if count:
            self.free_flight_acceleration.copy_(torch.as_tensor(total / count))

    def free_of_contact(self, poses: torch.Tensor) -> torch.Tensor:
        """[..., K] True where no vertex of the body is within the contact distance of the floor or the collision
        radius of another body's vertex (NaN poses count as in contact)."""
        vertices = self.bodies.vertices(poses)  # [..., n, 3]
        near_floor = ~(self.clearance(vertices) >= self.contact_distance)
        gap = torch.cdist(vertices.flatten(0, -3), vertices.flatten(0, -3)).reshape(
            *vertices.shape[:-1], vertices.shape[-2]
        )
        other = self.node_body[:, None] != self.node_body[None, :]
        near_other = ((gap < self.radius) & other).any(dim=-1)
        gated = (near_floor | near_other).double()
        in_contact = torch.zeros(*gated.shape[:-1], self.scene.n_bodies, dtype=torch.float64).index_add_(
            -1, self.node_body, gated
        )
        return in_contact == 0

    # ------------------------------------------------------------ one step

    def node_features_double(self, vertices: torch.Tensor) -> torch.Tensor:
        """The paper's node features (velocities differenced in float64 before the float32 network sees them), and two
        finer heights in units of the contact distance: now, and at the next frame if the vertex flew on freely
        (h + (v_z + g_z dt) dt, negative when the next step would reach the floor: where an impact is decided)."""
        batch, _, n_nodes, _ = vertices.shape
        if self.ground.flat:
            height = vertices[:, -1, :, 2:] - self.floor_z
            vertical_speed = (vertices[:, -1, :, 2:] - vertices[:, -2, :, 2:]) / self.dt
            free_flight = height + (vertical_speed + self.scene_gravity[2] * self.dt) * self.dt
        else:
            height = self.clearance(vertices[:, -1])[..., None]
            free_flight = self.clearance(self.free_flight_step(vertices))[..., None]
        fine = (torch.cat([height, free_flight], dim=-1) / self.contact_distance).clamp(min=-1.0, max=1.0)
        paper = self.node_features(vertices).reshape(batch, n_nodes, -1)
        return torch.cat([paper, fine], dim=-1).flatten(0, 1).float()

    def free_flight_step(self, vertices: torch.Tensor) -> torch.Tensor:
        """Where the newest vertices [B, n, 3] of a history [B, H + 1, n, 3] are a frame later in free flight."""
        velocity = (vertices[:, -1] - vertices[:, -2]) / self.dt + self.scene_gravity * self.dt
        return vertices[:, -1] + velocity * self.dt

    def edge_features(self, current: torch.Tensor, edge_index: torch.Tensor, n_mesh_edges: int) -> torch.Tensor:
        """The paper's 9 edge features, and on collision edges how deep the receiver is inside the sender's body.

        For a convex body the largest signed distance of a point to its face planes is the point's signed distance
        to the body where it is inside (−penetration depth) and a lower bound outside: the receiver's depth (in
        collision radii, clipped to ±1) and the outward normal of that face tell the network what a vertex-face
        contact needs, which vertex-vertex distances alone leave to guesswork (Allen et al. 2022's face edges).
        """
        base = super().edge_features(current, edge_index, n_mesh_edges)
        senders, receivers = edge_index[:, n_mesh_edges:]
        n_nodes = current.shape[1]
        graphs = receivers // n_nodes
        triangles = current[:, self.faces]  # [B, F, 3 corners, 3]
        normals = torch.linalg.cross(
            triangles[:, :, 1] - triangles[:, :, 0], triangles[:, :, 2] - triangles[:, :, 0], dim=-1
        )
        normals = normals / torch.linalg.vector_norm(normals, dim=-1, keepdim=True)
        offsets = (normals * triangles[:, :, 0]).sum(-1)
        points = current.flatten(0, 1)[receivers]
        distances = torch.einsum("efc,ec->ef", normals[graphs], points) - offsets[graphs]
        own_faces = self.face_body[None, :] == self.node_body[senders % n_nodes][:, None]
        depth, face = distances.masked_fill(~own_faces, -torch.inf).max(dim=-1)
        extra = base.new_zeros(base.shape[0], self.extra_edge_features)
        extra[n_mesh_edges:, 0] = (depth / self.radius).clamp(-1.0, 1.0)
        extra[n_mesh_edges:, 1:] = normals[graphs, face]
        return torch.cat([base, extra], dim=-1)

    def accelerations(self, poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Centre-of-mass linear and world angular accelerations [B, K, 3] (float64) from poses [B, H + 1, K, 7]."""
        vertices = self.bodies.vertices(poses)
        current = vertices[:, -1]
        current_single = current.float()
        edge_index, n_mesh_edges = build_edges(current_single, self.node_body, self.mesh_edges, self.radius)
        output = self.network(
            self.node_features_double(vertices),
            edge_index,
            self.edge_features(current_single, edge_index, n_mesh_edges),
        ).reshape(current.shape)
        height = self.clearance(current)
        if self.floor_gate is None:
            near = height < self.contact_distance
        else:  # within floor_gate of the floor now, or at the next frame if it flew on freely
            if self.ground.flat:
                following = (
                    height
                    + ((current[..., 2] - vertices[:, -2, :, 2]) / self.dt + self.scene_gravity[2] * self.dt) * self.dt
                )
            else:
                following = self.clearance(self.free_flight_step(vertices))
            near = torch.minimum(height, following) < self.floor_gate
        touched = torch.zeros(current.shape[0] * current.shape[1], dtype=torch.bool, device=current.device)
        touched[edge_index[1, n_mesh_edges:]] = True
        gate = near | touched.reshape(near.shape)
        contact = output.double() * self.acceleration_std.double() * gate[..., None]
        linear, angular = self.bodies.rigid_fit(contact, current, poses[:, -1])
        linear = linear + self.free_flight_acceleration
        return self.bodies.jointed(poses, linear, angular) if self.bodies.joints else (linear, angular)

    def step(self, history: torch.Tensor) -> torch.Tensor:
        """The pose frame [B, K, 7] after poses [B, H + 1, K, 7], with the predicted accelerations (bodies pushed apart,
        when the simulator separates them)."""
        following = self.bodies.integrate(history, *self.accelerations(history))
        if self.bodies.separates:
            following = self.bodies.separate(following)
        return self.bodies.keep_joints(following) if self.bodies.joints else following

    # ------------------------------------------------------------ training

    def with_noise(
        self, inputs: torch.Tensor, following: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Random-walk noise on input positions and orientations; the target frame moves with the last input's."""
        shift = random_walk_noise(inputs[..., :3], self.noise_std, generator)
        turn = (
            random_walk_noise(torch.zeros_like(inputs[..., :3]), 1.0, generator)
            * (self.noise_std / self.half_widths)[:, None]
        )
        inputs = torch.cat(
            [inputs[..., :3] + shift, quaternions.multiply(quaternions.from_rotation_vector(turn), inputs[..., 3:])],
            dim=-1,
        )
        following = torch.cat(
            [
                following[..., :3] + shift[:, -1],
                quaternions.multiply(quaternions.from_rotation_vector(turn[:, -1]), following[..., 3:]),
            ],
            dim=-1,
        )
        return inputs, following

    def loss(self, window: torch.Tensor, add_noise: bool, generator: torch.Generator | None = None) -> torch.Tensor:
        """MSE of the implied vertex accelerations a + α × r_i, normalised per axis, for pose windows [B, H + 2, K,
        7]."""
        window = window.double()
        inputs, following = window[:, :-1], window[:, -1]
        if add_noise and self.noise_std > 0:
            inputs, following = self.with_noise(inputs, following, generator)
        linear, angular = self.accelerations(inputs)
        target_linear, target_angular = self.bodies.target_accelerations(inputs[:, -2], inputs[:, -1], following)
        offsets = self.bodies.vertices(inputs[:, -1]) - inputs[:, -1, self.node_body, :3]
        error = (linear - target_linear)[:, self.node_body] + torch.linalg.cross(
            (angular - target_angular)[:, self.node_body], offsets, dim=-1
        )
        return torch.mean(torch.square(error / self.acceleration_std.double())).float()

    # ------------------------------------------------------------ rollouts

    @torch.no_grad()
    def rollout(self, context: torch.Tensor, n_steps: int) -> torch.Tensor:
        """The n_steps pose frames [B, n_steps, K, 7] after context poses [B, C, K, 7] (float64)."""
        history = context[:, -(self.velocity_history + 1) :]
        predicted = []
        for _ in range(n_steps):
            following = self.step(history)
            predicted.append(following)
            history = torch.cat([history[:, 1:], following[:, None]], dim=1)
        return torch.stack(predicted, dim=1) if predicted else context[:, :0]


class RigidGNNContactModel(ContactModel):
    """A trained rigid simulator as a contact model: rigid poses straight from the rollout, no projection after."""

    name = "gnn"

    def __init__(self, simulator: RigidLearnedSimulator, batch_size: int = 256):
        self.simulator = simulator
        self.batch_size = batch_size

    def rollout(self, scene: Scene, context: Context) -> np.ndarray:
        check_same_scene(self.simulator, scene, context)
        n_steps = context.horizon - context.n_context
        device = self.simulator.rest_vertices.device
        predicted = [
            self.simulator.rollout(
                torch.as_tensor(context.poses[start : start + self.batch_size], device=device), n_steps
            )
            .cpu()
            .numpy()
            for start in range(0, context.poses.shape[0], self.batch_size)
        ]
        return np.concatenate([context.poses, np.concatenate(predicted)], axis=1)
