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
  as for every benchmark solid and the real cube). Frictioncubes μ = 0.5, val position 0.281 -> 0.199 widths; the
  real cube, whose impacts and tracking are not PyBullet's, 0.218 -> 0.295 (commit a754e2c).
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

import itertools

import numpy as np
import torch

from contactbench import metrics
from contactbench.meshes import Mesh
from contactbench.metrics import PARALLEL_EDGE_SINE
from contactbench.models.base import ContactModel
from contactbench.models.gnn import quaternions
from contactbench.models.gnn.graph import MeshScene, build_edges
from contactbench.models.gnn.simulator import STATISTICS_CHUNK, LearnedSimulator, check_same_scene, random_walk_noise
from contactbench.protocol import Context
from contactbench.scene import Joint, Scene, Split

SEPARATION_SWEEPS = 4  # Jacobi sweeps of the pairwise separation: enough for a stack of five


def separating_axes(scene: MeshScene) -> tuple[torch.Tensor, torch.Tensor]:
    """Every body's distinct face normals [K, F, 3] and edge directions [K, E, 3] in its mesh frame, each list padded
    to the longest (padded_rows)."""
    geometries = []
    for body, nodes in enumerate(scene.body_slices()):
        faces = scene.faces[scene.node_body[scene.faces[:, 0]] == body] - nodes.start
        try:
            geometries.append(metrics.convex_geometry(Mesh(scene.rest_vertices[nodes], faces), body))
        except ValueError as error:
            raise ValueError(f"{error}; separate_bodies=true needs convex bodies (set it false)") from None

    return padded_rows([g.face_normals for g in geometries]), padded_rows([g.edge_directions for g in geometries])


def tangents(axis: np.ndarray) -> np.ndarray:
    """Two unit vectors [2, 3] orthogonal to a unit axis and to each other."""
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    first = np.cross(axis, helper)
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(axis, first)])


def skew(vectors: torch.Tensor) -> torch.Tensor:
    """The cross-product matrices [..., 3, 3] of vectors [..., 3]: skew(r) w = r × w."""
    x, y, z = vectors.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*vectors.shape[:-1], 3, 3)


def in_world(orientations: torch.Tensor, matrices: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """Body-axes matrices [K, 3, 3] applied to world vectors [..., K, 3] of bodies at orientations [..., K, 4]:
    R M Rᵀ v."""
    in_body = quaternions.rotate(quaternions.conjugate(orientations), vectors)
    return quaternions.rotate(orientations, (matrices @ in_body[..., None])[..., 0])


def padded_rows(rows: list) -> torch.Tensor:
    """Arrays (or slices, as their indices) of different lengths stacked, each padded to the longest by repeating
    its first entry: a repeated axis or vertex changes no separating-axis test."""
    rows = [np.arange(row.start, row.stop) if isinstance(row, slice) else np.asarray(row) for row in rows]
    longest = max(len(row) for row in rows)
    return torch.as_tensor(np.stack([np.concatenate([row, row[:1].repeat(longest - len(row), 0)]) for row in rows]))


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
        self.joints = tuple(joints)  # parents first (Scene.joints)
        self.floor_gate = floor_gate
        super().__init__(scene, dt, floor_z, radius, **options)
        node_body = torch.as_tensor(scene.node_body)
        rest = torch.as_tensor(scene.rest_vertices, dtype=torch.float64)
        counts = torch.bincount(node_body).to(torch.float64)
        centroids = torch.zeros(scene.n_bodies, 3, dtype=torch.float64).index_add_(0, node_body, rest) / counts[:, None]
        offsets = rest - centroids[node_body]
        spread = torch.einsum("ni,nj->nij", offsets, offsets)
        second_moment = torch.zeros(scene.n_bodies, 3, 3, dtype=torch.float64).index_add_(0, node_body, spread)
        geometric_inertia = (
            torch.diagonal(second_moment, dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3) - second_moment
        )
        self.register_buffer("rest_vertices_double", rest, persistent=False)
        self.register_buffer("rest_centroids", centroids, persistent=False)
        self.register_buffer("vertex_counts", counts, persistent=False)
        if solid_inertia is not None:  # per unit mass, about the vertex centroid: outputs act as forces on the solid
            geometric_inertia = counts[:, None, None] * torch.as_tensor(np.asarray(solid_inertia, dtype=np.float64))
        self.register_buffer("inverse_geometric_inertia", torch.linalg.inv(geometric_inertia), persistent=False)
        body_masses = np.ones(scene.n_bodies) if masses is None else np.asarray(masses, dtype=np.float64)
        self.register_buffer("body_masses", torch.as_tensor(body_masses), persistent=False)
        self.register_buffer("scene_gravity", torch.as_tensor(np.asarray(gravity, dtype=np.float64)), persistent=False)
        self.register_buffer("half_widths", torch.as_tensor(scene.widths / 2, dtype=torch.float64), persistent=False)
        # the acceleration of bodies in free flight, measured on the train split (fit_normalisation); meta's until then
        self.register_buffer("free_flight_acceleration", torch.as_tensor(np.asarray(gravity, dtype=np.float64)))
        self.register_buffer("faces", torch.as_tensor(scene.faces), persistent=False)
        self.register_buffer("face_body", torch.as_tensor(scene.node_body[scene.faces[:, 0]]), persistent=False)
        self.register_buffer("identity", torch.eye(3, dtype=torch.float64), persistent=False)
        self.register_buffer(
            "inverse_inertia_per_mass", self.inverse_geometric_inertia * counts[:, None, None], persistent=False
        )
        axes = np.array([joint.axis for joint in self.joints], dtype=np.float64).reshape(-1, 3)
        self.register_buffer("joint_axes", torch.as_tensor(axes), persistent=False)
        self.register_buffer(
            "joint_tangents", torch.as_tensor(np.array([tangents(a) for a in axes]).reshape(-1, 2, 3)), persistent=False
        )
        anchors = [[joint.parent_anchor, joint.child_anchor] for joint in self.joints]
        self.register_buffer(
            "joint_anchors", torch.as_tensor(np.array(anchors, dtype=np.float64).reshape(-1, 2, 3)), persistent=False
        )
        # a hinge holds its two links together: pushing them apart by translation would only fight keep_joints, so
        # the network (collision edges) and the joint's reaction keep jointed links apart
        jointed = {frozenset((joint.parent, joint.child)) for joint in self.joints}
        pairs = [pair for pair in itertools.combinations(range(scene.n_bodies), 2) if frozenset(pair) not in jointed]
        self.separates = separate_bodies and bool(pairs)
        if self.separates:
            normals, edges = separating_axes(scene)
            self.register_buffer("face_normals", normals, persistent=False)
            self.register_buffer("edge_directions", edges, persistent=False)
            self.register_buffer("body_pairs", torch.as_tensor(pairs).T, persistent=False)  # [2, P] (a, b), a < b
            self.register_buffer("body_vertices", padded_rows(scene.body_slices()), persistent=False)

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
        vertices = self.vertices(poses)  # [..., n, 3]
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

    # ------------------------------------------------------------ kinematics

    def vertices(self, poses: torch.Tensor) -> torch.Tensor:
        """World vertex positions [..., n, 3] of poses [..., K, 7] (float64)."""
        body_poses = poses[..., self.node_body, :]
        return body_poses[..., :3] + quaternions.rotate(body_poses[..., 3:], self.rest_vertices_double)

    def velocities(self, previous: torch.Tensor, current: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Backward-difference linear and world angular velocities [..., K, 3] between two pose frames."""
        linear = (current[..., :3] - previous[..., :3]) / self.dt
        return linear, quaternions.angular_velocity(previous[..., 3:], current[..., 3:], self.dt)

    def per_body_sum(self, values: torch.Tensor) -> torch.Tensor:
        """[B, n, ...] summed over each body's nodes -> [B, K, ...]."""
        out = values.new_zeros(values.shape[0], self.scene.n_bodies, *values.shape[2:])
        return out.index_add_(1, self.node_body, values)

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
        vertices = self.vertices(poses)
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
        linear, angular = self.rigid_fit(contact, current, poses[:, -1])
        linear = linear + self.free_flight_acceleration
        return self.jointed(poses, linear, angular) if self.joints else (linear, angular)

    def rigid_fit(
        self, vertex_accelerations: torch.Tensor, vertices: torch.Tensor, poses: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The rigid accelerations (centre of mass [B, K, 3], angular [B, K, 3]) nearest per-vertex ones, least squares.

        vertex_accelerations, vertices [B, n, 3]; poses [B, K, 7] the bodies' current poses (float64). Centripetal
        terms are left out: the fit is of accelerations relative to the current rotation, which the integrator adds.
        """
        centroids = self.per_body_sum(vertices) / self.vertex_counts[:, None]
        offsets = vertices - centroids[:, self.node_body]
        orientations = poses[..., 3:]
        moments = self.per_body_sum(torch.linalg.cross(offsets, vertex_accelerations, dim=-1))
        angular = in_world(orientations, self.inverse_geometric_inertia, moments)
        at_centroid = self.per_body_sum(vertex_accelerations) / self.vertex_counts[:, None]
        return at_centroid + torch.linalg.cross(angular, poses[..., :3] - centroids, dim=-1), angular

    def integrate(
        self, history: torch.Tensor, linear_acceleration: torch.Tensor, angular_acceleration: torch.Tensor
    ) -> torch.Tensor:
        """The pose frame [B, K, 7] after poses [B, H + 1, K, 7] under the given accelerations (semi-implicit Euler)."""
        velocity, spin = self.velocities(history[:, -2], history[:, -1])
        velocity = velocity + linear_acceleration * self.dt
        spin = spin + angular_acceleration * self.dt
        position = history[:, -1, :, :3] + velocity * self.dt
        orientation = quaternions.multiply(quaternions.from_rotation_vector(spin * self.dt), history[:, -1, :, 3:])
        return torch.cat([position, orientation / torch.linalg.vector_norm(orientation, dim=-1, keepdim=True)], dim=-1)

    def step(self, history: torch.Tensor) -> torch.Tensor:
        """The pose frame [B, K, 7] after poses [B, H + 1, K, 7], with the predicted accelerations (bodies pushed apart,
        when the simulator separates them)."""
        following = self.integrate(history, *self.accelerations(history))
        if self.separates:
            following = self.separate(following)
        return self.keep_joints(following) if self.joints else following

    # ------------------------------------------------------------ joints kept

    def jointed(
        self, poses: torch.Tensor, linear: torch.Tensor, angular: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The accelerations [B, K, 3] of the jointed bodies under free-body accelerations (contact and gravity) and
        each hinge's recorded damping, its reaction included: the impulse of least kinetic energy (Gauss) that keeps
        every hinge's anchors where they are relative to each other over the step and its two axes turning together.

        The network then learns contact alone; the joint's reaction, which swings a link on its neighbour, is
        Newton-Euler's. A step's anchor motion is taken exactly (exp(ω dt) r), linearised once about the unconstrained
        step (a Newton step, exact to O(dt²) of the correction), so a spinning elbow keeps its hinge without the
        centripetal error of a velocity-level constraint; what remains, keep_joints closes in rollouts. The gap the
        inputs carry is kept, not closed: training noise moves the target frame with the last input, gap included.
        """
        current = poses[:, -1]
        velocity, spin = self.velocities(poses[:, -2], current)
        orientations = current[..., 3:]
        following_velocity = velocity + linear * self.dt
        following_spin = spin + angular * self.dt + self.spin_change(orientations, self.damping_torques(current, spin))
        rows, residuals = self.joint_rows(current, following_velocity, following_spin)  # [B, R, K, 6], [B, R]
        # each row's impulse turned into the bodies' velocity changes: M⁻¹ Jᵀ
        mobility = torch.cat(
            [rows[..., :3] / self.body_masses[:, None], self.spin_change(orientations[:, None], rows[..., 3:])], dim=-1
        )
        impulses = torch.linalg.solve(torch.einsum("brkd,bskd->brs", rows, mobility), -residuals)
        change = torch.einsum("brkd,br->bkd", mobility, impulses)
        return (
            (following_velocity + change[..., :3] - velocity) / self.dt,
            (following_spin + change[..., 3:] - spin) / self.dt,
        )

    def spin_change(self, orientations: torch.Tensor, impulses: torch.Tensor) -> torch.Tensor:
        """The change of each body's spin [..., K, 3] under angular impulses [..., K, 3] (world axes): I⁻¹ in world."""
        return in_world(orientations, self.inverse_inertia_per_mass, impulses) / self.body_masses[:, None]

    def damping_torques(self, current: torch.Tensor, spin: torch.Tensor) -> torch.Tensor:
        """Each hinge's damping −c q̇ at the step's start, as angular impulses over the step [B, K, 3], equal and
        opposite on its two bodies (explicit, as the generator applies it)."""
        impulses = torch.zeros_like(spin)
        for joint, axis in zip(self.joints, self.joint_axes):
            axis = quaternions.rotate(current[:, joint.parent, 3:], axis)
            rate = ((spin[:, joint.child] - spin[:, joint.parent]) * axis).sum(-1, keepdim=True)
            impulses[:, joint.child] -= joint.damping * rate * axis * self.dt
            impulses[:, joint.parent] += joint.damping * rate * axis * self.dt
        return impulses

    def joint_rows(
        self, current: torch.Tensor, velocity: torch.Tensor, spin: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Every hinge's five constraint rows [B, 5 J, K, 6] on the bodies' (velocity, spin) over the coming step, and
        their residuals [B, 5 J] at the given ones: three for the anchors' relative displacement over the step
        (per unit time, exp(ω dt) r exact, its Jacobian at the rotated offsets), two for the relative spin across the
        axis (the child turns about the axis alone)."""
        batch = current.shape[0]
        rows = current.new_zeros(batch, 5 * len(self.joints), self.scene.n_bodies, 6)
        residuals = []
        eye = self.identity
        for j, (joint, tangents) in enumerate(zip(self.joints, self.joint_tangents)):
            anchor, cross = 5 * j, 5 * j + 3
            moves = []
            for body, anchor_offset, sign in (
                (joint.child, self.joint_anchors[j, 1], 1.0),
                (joint.parent, self.joint_anchors[j, 0], -1.0),
            ):
                offset = quaternions.rotate(current[:, body, 3:], anchor_offset)
                turned = quaternions.rotate(quaternions.from_rotation_vector(spin[:, body] * self.dt), offset)
                moves.append(sign * (velocity[:, body] + (turned - offset) / self.dt))
                rows[:, anchor:cross, body, :3] = sign * eye
                rows[:, anchor:cross, body, 3:] = -sign * skew(turned)
            world_tangents = quaternions.rotate(current[:, joint.parent, None, 3:], tangents)  # [B, 2, 3]
            rows[:, cross : cross + 2, joint.child, 3:] = world_tangents
            rows[:, cross : cross + 2, joint.parent, 3:] = -world_tangents
            relative_spin = spin[:, joint.child] - spin[:, joint.parent]
            residuals += [moves[0] + moves[1], (world_tangents @ relative_spin[..., None])[..., 0]]
        return rows, torch.cat(residuals, dim=-1)

    def keep_joints(self, poses: torch.Tensor) -> torch.Tensor:
        """Poses [B, K, 7] with every hinge closed, parents first: the child turned onto the nearest pure turn about
        the axis relative to its parent, then both moved along the anchors' gap in inverse proportion to their masses
        (the centre of mass of the pair stays where the network put it). A position projection like `separate`: the
        next step's differenced velocities follow the joint."""
        poses = poses.clone()
        for joint, axis, (parent_anchor, child_anchor) in zip(self.joints, self.joint_axes, self.joint_anchors):
            parent, child = poses[:, joint.parent], poses[:, joint.child]
            relative = quaternions.multiply(quaternions.conjugate(parent[:, 3:]), child[:, 3:])
            half_angle = torch.atan2(relative[:, 1:] @ axis, relative[:, 0])[:, None]
            turn = torch.cat([torch.cos(half_angle), torch.sin(half_angle) * axis], dim=-1)
            child_orientation = quaternions.multiply(parent[:, 3:], turn)
            anchors = [
                parent[:, :3] + quaternions.rotate(parent[:, 3:], parent_anchor),
                child[:, :3] + quaternions.rotate(child_orientation, child_anchor),
            ]
            gap = anchors[1] - anchors[0]
            masses = self.body_masses[joint.parent], self.body_masses[joint.child]
            parent_share = masses[1] / (masses[0] + masses[1])
            poses[:, joint.parent, :3] = parent[:, :3] + parent_share * gap
            poses[:, joint.child, :3] = child[:, :3] - (1 - parent_share) * gap
            poses[:, joint.child, 3:] = child_orientation
        return poses

    # ------------------------------------------------------------ bodies apart

    def separate(self, poses: torch.Tensor) -> torch.Tensor:
        """Poses [B, K, 7] translated (never turned) until no two bodies overlap.

        Position-based projection, as rigidity is kept by construction: only the newest frame moves, so the velocity
        the next step differences loses the approach speed that carried the bodies into each other (an inelastic
        contact, no energy gained beyond the depth of one step). Each overlapping pair is pushed apart by its exact
        penetration depth along the separating-axis test's axis of least overlap (the shortest translation that frees
        two convex bodies; vertex–face tests alone miss crossed edges), half each, in a few Jacobi sweeps (stacks).
        The floor is left to the network: lifting bodies out of it as well made single cubes bounce (frictioncubes
        μ = 0.5, test position 0.25 -> 0.37 widths), and a lift that also removes the approach speed wrecked them
        (val 0.20 -> 0.90) on weights trained without it; the network resolves most of that depth itself.
        """
        first, second = self.body_pairs
        for _ in range(SEPARATION_SWEEPS):
            depth, direction = self.least_overlap(poses, self.vertices(poses))
            if not bool((depth > 0).any()):
                break
            push = depth.clamp(min=0.0)[..., None] * direction / 2  # [B, P, 3]
            shift = torch.zeros_like(poses[..., :3]).index_add_(1, second, push).index_add_(1, first, -push)
            poses = torch.cat([poses[..., :3] + shift, poses[..., 3:]], dim=-1)
        return poses

    def least_overlap(self, poses: torch.Tensor, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every body pair's (a, b) overlap [B, P] along its separating-axis test's axis of least overlap, and the
        unit direction [B, P, 3] that moving b by the overlap frees it (negative overlap: the bodies are apart)."""
        first, second = self.body_pairs
        orientation_a, orientation_b = poses[:, first, None, 3:], poses[:, second, None, 3:]  # [B, P, 1, 4]
        edges_a = quaternions.rotate(orientation_a, self.edge_directions[first])
        edges_b = quaternions.rotate(orientation_b, self.edge_directions[second])
        crossed = torch.linalg.cross(edges_a[:, :, :, None], edges_b[:, :, None], dim=-1).flatten(2, 3)
        sines = torch.linalg.vector_norm(crossed, dim=-1, keepdim=True)
        axes = torch.cat(
            [
                quaternions.rotate(orientation_a, self.face_normals[first]),
                quaternions.rotate(orientation_b, self.face_normals[second]),
                crossed / sines.clamp(min=PARALLEL_EDGE_SINE),
            ],
            dim=2,
        )  # [B, P, M, 3]
        projected_a = vertices[:, self.body_vertices[first]] @ axes.transpose(-1, -2)  # [B, P, V, M]
        projected_b = vertices[:, self.body_vertices[second]] @ axes.transpose(-1, -2)
        overlaps = torch.cat(
            [
                projected_a.amax(dim=2) - projected_b.amin(dim=2),  # b freed by moving along +axis
                projected_b.amax(dim=2) - projected_a.amin(dim=2),  # along −axis
            ],
            dim=2,
        )
        n_axes = axes.shape[2]
        parallel = torch.zeros(sines.shape[:2] + (n_axes,), dtype=torch.bool, device=axes.device)
        parallel[..., n_axes - crossed.shape[2] :] = sines[..., 0] < PARALLEL_EDGE_SINE
        depth, chosen = overlaps.masked_fill(torch.cat([parallel, parallel], dim=2), torch.inf).min(dim=2)
        sign = 1.0 - 2.0 * (chosen >= n_axes).to(axes.dtype)
        direction = torch.gather(axes, 2, (chosen % n_axes)[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]
        return depth, direction * sign[..., None]

    # ------------------------------------------------------------ training

    def target_accelerations(
        self, previous: torch.Tensor, current: torch.Tensor, following: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The accelerations [B, K, 3] that take the step from `current` to `following` (recorded poses)."""
        velocity, spin = self.velocities(previous, current)
        next_velocity, next_spin = self.velocities(current, following)
        return (next_velocity - velocity) / self.dt, (next_spin - spin) / self.dt

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
        target_linear, target_angular = self.target_accelerations(inputs[:, -2], inputs[:, -1], following)
        offsets = self.vertices(inputs[:, -1]) - inputs[:, -1, self.node_body, :3]
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
