"""The paper's evaluation metrics (§4.1, §5.2): pose errors, floor and inter-body penetration, pairwise collisions, eq.
(1)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from contactbench import rotations
from contactbench.ground import Ground, signed_distance
from contactbench.kinematics import hinge_errors, world_vertices
from contactbench.meshes import Mesh
from contactbench.protocol import scored_frames, trajectory_means
from contactbench.scene import Joint

# Two edges whose directions' cross product is shorter than this (the sine of their angle) are treated as parallel:
# their cross product names no axis, and the faces of both bodies already cover that configuration.
PARALLEL_EDGE_SINE = 1e-6
# Unit normals or directions closer than this to (anti)parallel are the same separating axis.
SAME_AXIS_COSINE = 1.0 - 1e-10
# A vertex further than this fraction of the body width outside a face plane makes the mesh non-convex.
CONVEXITY_TOLERANCE = 1e-6
# Floats per array in one chunk of the separating-axis test; bounds memory for meshes with many edges.
CHUNK_FLOATS = 1 << 21


@dataclass
class MetricsResult:
    summary: dict[str, float | None]  # means over trajectories of the per-trajectory values (see compute_metrics)
    per_frame: dict[str, np.ndarray]  # [T] curves at absolute frame indices, NaN where nothing is scored
    per_trajectory: dict[str, np.ndarray]  # [N] per-trajectory values


# ---------------------------------------------------------------- per-frame, per-object errors


def _check_pose_pair(true_poses: np.ndarray, pred_poses: np.ndarray, widths: np.ndarray | None = None) -> None:
    """A ValueError naming the shapes unless two pose arrays [..., K, 7] broadcast (and widths are [K])."""
    if true_poses.shape[-1:] != (7,) or pred_poses.shape[-1:] != (7,) or true_poses.ndim < 2 or pred_poses.ndim < 2:
        raise ValueError(f"poses must be [..., K, 7]; got true {true_poses.shape} and pred {pred_poses.shape}")
    try:
        shape = np.broadcast_shapes(true_poses.shape, pred_poses.shape)
    except ValueError:
        raise ValueError(
            f"true poses {true_poses.shape} and predicted poses {pred_poses.shape} do not broadcast"
        ) from None
    if true_poses.shape[-2] != pred_poses.shape[-2]:
        raise ValueError(
            f"true poses {true_poses.shape} and predicted poses {pred_poses.shape} have different body counts"
        )
    if widths is not None and widths.shape != (shape[-2],):
        raise ValueError(f"widths {widths.shape} do not match the {shape[-2]} bodies of poses {shape}")


def position_error(true_poses, pred_poses, widths) -> np.ndarray:
    """‖x̄ − x̂‖ / w_k per body: poses [..., K, 7] (broadcasting), widths [K]; returns [..., K]."""
    true_poses, pred_poses, widths = (
        np.asarray(true_poses, float),
        np.asarray(pred_poses, float),
        np.asarray(widths, float),
    )
    _check_pose_pair(true_poses, pred_poses, widths)
    return np.linalg.norm(true_poses[..., :3] - pred_poses[..., :3], axis=-1) / widths


def rotation_error(true_poses, pred_poses) -> np.ndarray:
    """Angle in [0, π] between true and predicted orientations per body (q ≡ −q, any quaternion scale); [..., K]."""
    true_poses, pred_poses = np.asarray(true_poses, float), np.asarray(pred_poses, float)
    _check_pose_pair(true_poses, pred_poses)
    return rotations.angle_between(true_poses[..., 3:], pred_poses[..., 3:])


def configuration_error(true_poses, pred_poses, widths, position_exponent: int = 1) -> np.ndarray:
    """Eq. (1), the SysID objective: Σ_k (2/w_k)^p ‖x̄_k − x̂_k‖² + angle(R̄_k, R̂_k)², per frame; returns [...].

    p = 1 is the paper's equation as printed; p = 2 makes the position term ((‖x̄ − x̂‖ / half-width)²)
    dimensionless like the angle term. Leading axes broadcast, e.g. pred [B, N, T, K, 7] against true
    [N, T, K, 7] gives [B, N, T].
    """
    true_poses, pred_poses, widths = (
        np.asarray(true_poses, float),
        np.asarray(pred_poses, float),
        np.asarray(widths, float),
    )
    _check_pose_pair(true_poses, pred_poses, widths)
    offset = true_poses[..., :3] - pred_poses[..., :3]
    positional = np.einsum("...i,...i->...", offset, offset) @ (2.0 / widths) ** position_exponent
    true_q, pred_q = true_poses[..., 3:], pred_poses[..., 3:]
    # angle = 2 atan2(|vector part of q̄* q̂|, |q̄·q̂|), that norm from Lagrange's identity |q̄|²|q̂|² − (q̄·q̂)²: five times
    # cheaper than the quaternion product, and its rounding (≈1e-8 rad near zero) is immaterial to a squared error.
    dot = np.einsum("...i,...i->...", true_q, pred_q)
    norms = np.einsum("...i,...i->...", true_q, true_q) * np.einsum("...i,...i->...", pred_q, pred_q)
    angle = 2.0 * np.arctan2(np.sqrt(np.maximum(norms - dot * dot, 0.0)), np.abs(dot))
    return positional + np.einsum("...k,...k->...", angle, angle)


def _check_poses_meshes(poses: np.ndarray, meshes: list[Mesh]) -> None:
    if poses.ndim < 2 or poses.shape[-1] != 7 or poses.shape[-2] != len(meshes):
        raise ValueError(f"poses {poses.shape} must be [..., K, 7] with K = {len(meshes)} meshes")


def _unit_quaternions(poses: np.ndarray) -> np.ndarray:
    """Poses with their quaternions normalised, so a slightly off-unit prediction places vertices as it orients them."""
    return np.concatenate([poses[..., :3], rotations.normalize(poses[..., 3:])], axis=-1)


def _lowest_vertex_z(poses: np.ndarray, meshes: list[Mesh]) -> np.ndarray:
    """World z of each body's lowest vertex: poses [..., K, 7] → [..., K]."""
    poses = _unit_quaternions(np.asarray(poses, float))
    _check_poses_meshes(poses, meshes)
    return np.stack(
        [world_vertices(poses[..., k, :], mesh.vertices)[..., 2].min(axis=-1) for k, mesh in enumerate(meshes)], axis=-1
    )


def floor_penetration(poses, meshes: list[Mesh], floor_z: float) -> np.ndarray:
    """max_j max(0, floor_z − z_j) over each body's mesh vertices: poses [..., K, 7] → [..., K] metres."""
    return np.maximum(0.0, floor_z - _lowest_vertex_z(poses, meshes))


def lowest_vertex_height(poses, meshes: list[Mesh], floor_z: float) -> np.ndarray:
    """min_j z_j − floor_z over each body's mesh vertices (negative when below the floor): [..., K] metres."""
    return _lowest_vertex_z(poses, meshes) - floor_z


def ground_clearance(poses, meshes: list[Mesh], ground: Ground) -> np.ndarray:
    """min_j of the ground's signed distance at each body's mesh vertices (its true surface, concavities included;
    negative inside the floor, a ramp, a step or a height field): poses [..., K, 7] → [..., K] metres."""
    if ground.flat:
        return lowest_vertex_height(poses, meshes, ground.floor_z)
    poses = _unit_quaternions(np.asarray(poses, float))
    _check_poses_meshes(poses, meshes)
    return np.stack(
        [
            signed_distance(ground, world_vertices(poses[..., k, :], mesh.vertices))[0].min(axis=-1)
            for k, mesh in enumerate(meshes)
        ],
        axis=-1,
    )


def joint_errors(poses, joints: list[Joint]) -> tuple[np.ndarray, np.ndarray]:
    """How far poses [..., K, 7] break each hinge: the distance between its two anchors (m) and the angle between its
    two axes (rad), each [..., J]."""
    return hinge_errors(_unit_quaternions(np.asarray(poses, float)), joints)


# ---------------------------------------------------------------- separating-axis test for convex bodies


@dataclass(frozen=True)
class ConvexGeometry:
    """What the separating-axis test needs of one convex mesh, in its body frame."""

    vertices: np.ndarray  # [V, 3]
    face_normals: np.ndarray  # [F, 3] unit, one per distinct face plane orientation (up to sign)
    edge_directions: np.ndarray  # [E, 3] unit, one per distinct direction of the edges between non-coplanar faces
    centre: np.ndarray  # [3] centre of the bounding sphere (of the vertex bounding box)
    radius: float  # bounding sphere radius about centre


def _distinct_axes(directions: np.ndarray) -> np.ndarray:
    """Unit directions [M, 3] with (anti)parallel repeats removed, first occurrence kept."""
    similar = np.abs(directions @ directions.T) > SAME_AXIS_COSINE
    return directions[~np.tril(similar, k=-1).any(axis=1)]


def convex_geometry(mesh: Mesh, body: int) -> ConvexGeometry:
    vertices = np.asarray(mesh.vertices, float)
    faces = np.asarray(mesh.faces, np.int64)
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    normals = cross / np.where(area2 > 0, area2, 1.0)[:, None]
    outside = (vertices @ normals.T - np.einsum("fi,fi->f", normals, corners[:, 0]))[:, area2 > 0]
    if outside.max() > CONVEXITY_TOLERANCE * mesh.width:
        raise ValueError(
            f"inter-body penetration needs convex meshes: body {body}'s mesh has a vertex {outside.max():.3g} m "
            f"outside one of its face planes"
        )
    # Each undirected edge borders two faces of a closed mesh; only edges between non-coplanar faces are real edges
    # of the polyhedron (a triangulated square's diagonal is not, and would only add redundant axes).
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    face_of = np.tile(np.arange(len(faces)), 3)
    keys = np.sort(directed, axis=1) @ np.array([len(vertices), 1])
    order = np.argsort(keys, kind="stable")
    if len(order) % 2 or np.any(keys[order[0::2]] != keys[order[1::2]]):
        raise ValueError(f"body {body}'s mesh is not closed: every edge must border exactly two faces")
    first, second = order[0::2], order[1::2]
    is_feature = np.einsum("ei,ei->e", normals[face_of[first]], normals[face_of[second]]) < SAME_AXIS_COSINE
    edge_vectors = np.diff(vertices[directed[first[is_feature]]], axis=1)[:, 0]
    edge_vectors /= np.linalg.norm(edge_vectors, axis=1, keepdims=True)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    centre = (low + high) / 2
    return ConvexGeometry(
        vertices=vertices,
        face_normals=_distinct_axes(normals[area2 > 0]),
        edge_directions=_distinct_axes(edge_vectors),
        centre=centre,
        radius=float(np.linalg.norm(vertices - centre, axis=1).max()),
    )


def _sat_separation(
    poses_a: np.ndarray, poses_b: np.ndarray, geometry_a: ConvexGeometry, geometry_b: ConvexGeometry
) -> np.ndarray:
    """Signed separation of two convex bodies at unit-quaternion poses [S, 7] each: max over candidate axes of the gap
    between the bodies' projection intervals, i.e. −(penetration depth) when they overlap; returns [S].

    Works in A's body frame, where A's vertices, face normals and edges stay fixed and only B's move.
    """
    n_face_axes = len(geometry_a.face_normals) + len(geometry_b.face_normals)
    n_axes = n_face_axes + len(geometry_a.edge_directions) * len(geometry_b.edge_directions)
    per_frame_floats = (3 + len(geometry_a.vertices) + len(geometry_b.vertices)) * n_axes
    chunk = max(1, CHUNK_FLOATS // per_frame_floats)
    separation = np.empty(len(poses_a))
    for begin in range(0, len(poses_a), chunk):
        part_a, part_b = poses_a[begin : begin + chunk], poses_b[begin : begin + chunk]
        rotation_a = rotations.to_matrix(part_a[:, 3:])
        b_to_a = rotation_a.transpose(0, 2, 1) @ rotations.to_matrix(part_b[:, 3:])
        offset_in_a = np.einsum("sji,sj->si", rotation_a, part_b[:, :3] - part_a[:, :3])
        edges_b = geometry_b.edge_directions @ b_to_a.transpose(0, 2, 1)
        edge_axes = np.cross(geometry_a.edge_directions[None, :, None, :], edges_b[:, None, :, :]).reshape(
            len(part_a), -1, 3
        )
        edge_sines = np.linalg.norm(edge_axes, axis=-1)
        is_parallel = edge_sines < PARALLEL_EDGE_SINE
        edge_axes /= np.where(is_parallel, 1.0, edge_sines)[..., None]
        axes = np.concatenate(
            [
                np.broadcast_to(geometry_a.face_normals, (len(part_a),) + geometry_a.face_normals.shape),
                geometry_b.face_normals @ b_to_a.transpose(0, 2, 1),
                edge_axes,
            ],
            axis=1,
        )
        # [s, V, M]: reducing over the middle (vertex) axis runs along whole rows of axes, much faster than a last axis.
        axes_t = axes.transpose(0, 2, 1)
        projected_a = geometry_a.vertices @ axes_t
        projected_b = (geometry_b.vertices @ b_to_a.transpose(0, 2, 1) + offset_in_a[:, None, :]) @ axes_t
        overlap = np.minimum(
            projected_a.max(axis=1) - projected_b.min(axis=1),
            projected_b.max(axis=1) - projected_a.min(axis=1),
        )
        overlap[:, n_face_axes:][is_parallel] = np.inf
        separation[begin : begin + chunk] = -overlap.min(axis=1)
    return separation


def pair_separation(poses_a, poses_b, mesh_a: Mesh, mesh_b: Mesh) -> np.ndarray:
    """Signed separation of two convex bodies by the exact separating-axis test; poses [..., 7] broadcast → [...].

    Negative values are −(penetration depth), the shortest translation that separates the bodies (exact). Positive
    values are the largest gap over the candidate axes: the distance itself when the closest features are a face and
    anything, or two non-parallel edges; a lower bound on it otherwise (e.g. two corners facing each other).
    """
    poses_a, poses_b = np.asarray(poses_a, float), np.asarray(poses_b, float)
    if poses_a.shape[-1:] != (7,) or poses_b.shape[-1:] != (7,):
        raise ValueError(f"poses must be [..., 7]; got {poses_a.shape} and {poses_b.shape}")
    try:
        shape = np.broadcast_shapes(poses_a.shape, poses_b.shape)
    except ValueError:
        raise ValueError(f"poses {poses_a.shape} and {poses_b.shape} do not broadcast") from None
    flat_a, flat_b = (_unit_quaternions(np.broadcast_to(poses, shape).reshape(-1, 7)) for poses in (poses_a, poses_b))
    return _sat_separation(flat_a, flat_b, convex_geometry(mesh_a, 0), convex_geometry(mesh_b, 1)).reshape(shape[:-1])


def _pairwise_separations(poses: np.ndarray, geometries: list[ConvexGeometry], cutoff: float) -> np.ndarray:
    """Separation of every body pair (itertools.combinations order) at unit-quaternion poses [S, K, 7] → [S, P];
    +inf where it certainly exceeds `cutoff`, which skips the full test for bodies that are far apart.

    The skip test projects the centre offset of the bounding spheres on the bodies' face normals, which are candidate
    axes of the full test: on each, the gap is at least |n·Δc| − r_a − r_b, so a skipped pair's separation is larger
    than `cutoff` and thresholds at or below `cutoff` give the same answers as the full test. NaN poses are never
    skipped, so they give NaN separations.
    """
    centres = np.stack([world_vertices(poses[:, k], g.centre[None])[:, 0] for k, g in enumerate(geometries)], axis=1)
    separations = []
    for a, b in itertools.combinations(range(len(geometries)), 2):
        offset = centres[:, b] - centres[:, a]
        offset_in_a = rotations.rotate(rotations.conjugate(poses[:, a, 3:]), offset)
        offset_in_b = rotations.rotate(rotations.conjugate(poses[:, b, 3:]), offset)
        largest_projection = np.maximum(
            np.abs(offset_in_a @ geometries[a].face_normals.T).max(axis=1),
            np.abs(offset_in_b @ geometries[b].face_normals.T).max(axis=1),
        )
        gap_bound = largest_projection - geometries[a].radius - geometries[b].radius
        pair = np.full(len(poses), np.inf)
        tested = ~(gap_bound > cutoff)
        pair[tested] = _sat_separation(poses[tested, a], poses[tested, b], geometries[a], geometries[b])
        separations.append(pair)
    return np.stack(separations, axis=-1)


def interbody_penetration(poses, meshes: list[Mesh]) -> np.ndarray:
    """Penetration depth of every body pair: poses [..., K, 7] → symmetric [..., K, K] metres, zero diagonal.

    The per-frame maximum of Fig. 7a is `.max(axis=(-2, -1))`.
    """
    poses = np.asarray(poses, float)
    _check_poses_meshes(poses, meshes)
    n_bodies = len(meshes)
    flat = _unit_quaternions(poses.reshape(-1, n_bodies, 7))
    geometries = [convex_geometry(mesh, k) for k, mesh in enumerate(meshes)]
    depth = np.zeros((len(flat), n_bodies, n_bodies))
    if n_bodies > 1:
        pair_depth = np.maximum(0.0, -_pairwise_separations(flat, geometries, cutoff=0.0))
        first, second = np.array(list(itertools.combinations(range(n_bodies), 2))).T
        depth[:, first, second] = pair_depth
        depth[:, second, first] = pair_depth
    return depth.reshape(poses.shape[:-2] + (n_bodies, n_bodies))


# ---------------------------------------------------------------- scoring protocol


def _scored_mask(
    true_poses: np.ndarray, pred_poses: np.ndarray, lengths: np.ndarray, start_frame: int, n_meshes: int
) -> np.ndarray:
    if true_poses.ndim != 4 or true_poses.shape[-1] != 7 or pred_poses.shape != true_poses.shape:
        raise ValueError(
            f"true poses {true_poses.shape} and predicted poses {pred_poses.shape} must both be [N, T, K, 7]"
        )
    n_trajectories, n_frames, n_bodies, _ = true_poses.shape
    if n_bodies != n_meshes:
        raise ValueError(f"poses {true_poses.shape} have {n_bodies} bodies but {n_meshes} meshes were given")
    if lengths.shape != (n_trajectories,):
        raise ValueError(f"lengths {lengths.shape} must be [N] for poses {true_poses.shape}")
    if start_frame < 0:
        raise ValueError(f"start_frame must be non-negative, got {start_frame}")
    if lengths.max(initial=0) > n_frames:
        worst = int(np.argmax(lengths))
        raise ValueError(
            f"trajectory {worst} has length {lengths[worst]} but poses {true_poses.shape} hold only {n_frames} frames"
        )
    if lengths.min(initial=n_frames) <= start_frame:
        short = int(np.argmin(lengths))
        raise ValueError(
            f"trajectory {short} has length {lengths[short]} <= start_frame {start_frame}: nothing to score"
        )
    return scored_frames(lengths, n_frames, start_frame)


def _aggregate(values: np.ndarray, scored: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-frame curve [T], per-trajectory means [N] and their mean, of values [S] at the scored frames [N, T]."""
    placed = np.zeros(scored.shape)
    placed[scored] = values
    per_trajectory = trajectory_means(placed, scored)
    counts = scored.sum(axis=0)
    per_frame = np.full(scored.shape[1], np.nan)
    per_frame[counts > 0] = placed.sum(axis=0)[counts > 0] / counts[counts > 0]
    return per_frame, per_trajectory, float(per_trajectory.mean())


def _pairs_touched(separations: np.ndarray, scored: np.ndarray, tolerance: float) -> np.ndarray:
    """Distinct pairs per trajectory whose separation is ≤ tolerance at some scored frame; NaN if any is NaN."""
    touching = np.zeros(scored.shape + separations.shape[-1:], dtype=bool)
    touching[scored] = separations <= tolerance
    undefined = np.zeros(scored.shape, dtype=bool)
    undefined[scored] = np.isnan(separations).any(axis=-1)
    count = touching.any(axis=1).sum(axis=-1).astype(float)
    count[undefined.any(axis=1)] = np.nan
    return count


def _undefined_if_not_finite(poses: np.ndarray) -> np.ndarray:
    """Poses [..., 7] with every component NaN where any is NaN or inf, so no metric can score a broken pose."""
    return np.where(np.isfinite(poses).all(axis=-1, keepdims=True), poses, np.nan)


def compute_metrics(
    true_poses,
    pred_poses,
    lengths,
    start_frame: int,
    meshes: list[Mesh],
    floor_z: float,
    contact_tolerance: float = 1e-3,
    ground: Ground | None = None,
    joints: list[Joint] = (),
) -> MetricsResult:
    """Score predicted poses [N, T, K, 7] against the truth on frames start_frame … lengths[n] − 1 of each trajectory.

    Per frame, pose errors, floor penetration (the prediction's, and the truth's own as floor_penetration_true_m)
    and lowest-vertex height are means over the bodies; inter-body
    penetration is the deepest pair. Per trajectory, the mean over its scored frames; summary, the mean over
    trajectories, so every toss weighs the same. Pairwise collisions count the distinct body pairs whose separation
    is ≤ contact_tolerance (m) at some scored frame, for the prediction and for the truth. Frames outside the scored
    range are never read and may hold anything. Inside it, a body pose with any NaN or inf component is undefined as a
    whole: it is not dropped but makes every metric of its frame, trajectory and the summary NaN (pairwise collisions
    of that trajectory too), so a diverging model cannot look good. Quaternions are normalised before vertices are
    placed. With a `ground` (terrain besides the floor at floor_z) penetration and lowest-vertex height are taken
    against it (ground_clearance); with `joints`, the hinges' anchor gap and axis angle (joint_errors, the largest
    over the joints) are scored too.
    """
    true_poses, pred_poses = np.asarray(true_poses, float), np.asarray(pred_poses, float)
    lengths = np.asarray(lengths)
    scored = _scored_mask(true_poses, pred_poses, lengths, int(start_frame), len(meshes))
    true_scored, pred_scored = (
        _undefined_if_not_finite(poses[scored]) for poses in (true_poses, pred_poses)
    )  # [S, K, 7]
    widths = np.array([mesh.width for mesh in meshes])

    def lowest_of(poses: np.ndarray) -> np.ndarray:
        if ground is None:
            return lowest_vertex_height(poses, meshes, floor_z)
        return ground_clearance(poses, meshes, ground)

    lowest = lowest_of(pred_scored)
    per_frame_values = {
        "pos_err": position_error(true_scored, pred_scored, widths).mean(axis=-1),
        "rot_err_rad": rotation_error(true_scored, pred_scored).mean(axis=-1),
        "floor_penetration_m": np.maximum(0.0, -lowest).mean(axis=-1),
        "min_vertex_height_m": lowest.mean(axis=-1),
        # the recording's own: PyBullet's sliding bodies sit millimetres below the floor, tracked real ones too
        "floor_penetration_true_m": np.maximum(0.0, -lowest_of(true_scored)).mean(axis=-1),
    }
    if joints:
        gaps, angles = joint_errors(pred_scored, list(joints))
        per_frame_values["joint_gap_m"] = gaps.max(axis=-1)
        per_frame_values["joint_axis_error_rad"] = angles.max(axis=-1)
    n_bodies = len(meshes)
    if n_bodies > 1:
        geometries = [convex_geometry(mesh, k) for k, mesh in enumerate(meshes)]
        pred_separations = _pairwise_separations(
            _unit_quaternions(pred_scored), geometries, max(contact_tolerance, 0.0)
        )
        true_separations = _pairwise_separations(_unit_quaternions(true_scored), geometries, contact_tolerance)
        per_frame_values["interbody_penetration_m"] = np.maximum(0.0, -pred_separations).max(axis=-1)

    summary: dict[str, float | None] = {}
    per_frame: dict[str, np.ndarray] = {}
    per_trajectory: dict[str, np.ndarray] = {}
    for name, values in per_frame_values.items():
        per_frame[name], per_trajectory[name], summary[name] = _aggregate(values, scored)
    per_frame["n_trajectories"] = scored.sum(axis=0)
    per_trajectory["length"] = lengths.astype(np.int64)
    if n_bodies > 1:
        per_trajectory["pairwise_collisions"] = _pairs_touched(pred_separations, scored, contact_tolerance)
        per_trajectory["pairwise_collisions_true"] = _pairs_touched(true_separations, scored, contact_tolerance)
        summary["pairwise_collisions"] = float(per_trajectory["pairwise_collisions"].mean())
        summary["pairwise_collisions_true"] = float(per_trajectory["pairwise_collisions_true"].mean())
    else:
        summary["interbody_penetration_m"] = None
        summary["pairwise_collisions"] = None
        summary["pairwise_collisions_true"] = None
    summary["scored_frames"] = int(scored.sum())
    return MetricsResult(summary=summary, per_frame=per_frame, per_trajectory=per_trajectory)
