"""Rigid-body dynamics of the rigid mesh GNN (rigid.py), apart from what it learns: per-vertex accelerations fitted as
one rigid acceleration per body, semi-implicit Euler on poses, each hinge's reaction and damping by Newton-Euler (the
least-kinetic-energy impulse that keeps it together) and its gap closed after a step, and overlapping convex bodies
pushed apart along the separating-axis test's axis of least overlap."""

from __future__ import annotations

import itertools

import numpy as np
import torch

from contactbench import metrics
from contactbench.meshes import Mesh
from contactbench.metrics import PARALLEL_EDGE_SINE
from contactbench.models.gnn import quaternions
from contactbench.models.gnn.graph import MeshScene
from contactbench.scene import Joint

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


class RigidBodies(torch.nn.Module):
    """The bodies of a mesh scene as rigid bodies: their vertices at given poses, the rigid accelerations nearest
    per-vertex ones, the semi-implicit Euler step, each hinge's reaction and damping (Newton-Euler), and bodies pushed
    apart by the separating-axis test. Its tensors are derived from the scene, never saved with the simulator."""

    def __init__(
        self,
        scene: MeshScene,
        dt: float,
        separate_bodies: bool = False,
        solid_inertia: np.ndarray | None = None,
        joints: tuple[Joint, ...] = (),
        masses: np.ndarray | None = None,
    ):
        super().__init__()
        self.dt = dt
        self.n_bodies = scene.n_bodies
        self.joints = tuple(joints)  # parents first (Scene.joints)
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
        self.register_buffer("node_body", node_body, persistent=False)
        self.register_buffer("rest_vertices_double", rest, persistent=False)
        self.register_buffer("rest_centroids", centroids, persistent=False)
        self.register_buffer("vertex_counts", counts, persistent=False)
        if solid_inertia is not None:  # per unit mass, about the vertex centroid: outputs act as forces on the solid
            geometric_inertia = counts[:, None, None] * torch.as_tensor(np.asarray(solid_inertia, dtype=np.float64))
        self.register_buffer("inverse_geometric_inertia", torch.linalg.inv(geometric_inertia), persistent=False)
        body_masses = np.ones(scene.n_bodies) if masses is None else np.asarray(masses, dtype=np.float64)
        self.register_buffer("body_masses", torch.as_tensor(body_masses), persistent=False)
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
        out = values.new_zeros(values.shape[0], self.n_bodies, *values.shape[2:])
        return out.index_add_(1, self.node_body, values)

    # ------------------------------------------------------------ Newton-Euler

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

    def target_accelerations(
        self, previous: torch.Tensor, current: torch.Tensor, following: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The accelerations [B, K, 3] that take the step from `current` to `following` (recorded poses)."""
        velocity, spin = self.velocities(previous, current)
        next_velocity, next_spin = self.velocities(current, following)
        return (next_velocity - velocity) / self.dt, (next_spin - spin) / self.dt

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
        rows = current.new_zeros(batch, 5 * len(self.joints), self.n_bodies, 6)
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
