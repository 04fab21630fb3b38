"""Hand-made checks of the metrics: pose errors, floor and inter-body penetration, collisions, aggregation, eq. (1)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from contactbench import metrics, rotations
from contactbench.generation.solids import WIDTH, convex_mesh, solid
from contactbench.kinematics import world_vertices
from contactbench.meshes import Mesh

CUBE = solid(6)  # 10.48 cm cube centred on its mesh frame
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def box(half_extents) -> Mesh:
    return convex_mesh(np.array(list(itertools.product(*[(-h, h) for h in half_extents]))))


def pose(position, quaternion=IDENTITY) -> np.ndarray:
    return np.concatenate([np.asarray(position, float), np.asarray(quaternion, float)])


def about_z(angle: float) -> np.ndarray:
    return rotations.from_axis_angle(np.array([0.0, 0.0, 1.0]), angle)


# ---------------------------------------------------------------- pose errors


def test_rotation_error_of_a_quarter_turn_is_half_pi_and_sign_of_quaternion_is_irrelevant():
    turned = pose([0, 0, 0], about_z(np.pi / 2))
    start = pose([0, 0, 0])
    assert metrics.rotation_error(start[None], turned[None])[0] == pytest.approx(np.pi / 2, abs=1e-12)
    flipped = pose([0, 0, 0], -turned[3:])
    assert metrics.rotation_error(turned[None], flipped[None])[0] == pytest.approx(0.0, abs=1e-12)
    half_turn = pose([0, 0, 0], rotations.from_axis_angle(np.array([1.0, 1.0, 0.0]), np.pi))
    assert metrics.rotation_error(start[None], half_turn[None])[0] == pytest.approx(np.pi, abs=1e-12)


def test_position_error_is_offset_over_width():
    assert CUBE.width == pytest.approx(0.1048)
    true = pose([0.3, -0.1, 0.2])[None]
    pred = pose([0.3, -0.1 + 0.0524, 0.2])[None]
    assert metrics.position_error(true, pred, [CUBE.width])[0] == pytest.approx(0.5)


def test_floor_penetration_and_lowest_vertex_height_use_the_lowest_mesh_vertex():
    floor_z = -0.002
    sunk = pose([0.0, 0.0, floor_z + WIDTH / 2 - 0.01])
    # Resting on an edge: a cube turned 45 degrees about x reaches WIDTH / sqrt(2) below its centre.
    on_edge = pose(
        [0.0, 0.0, floor_z + WIDTH / np.sqrt(2) + 0.003], rotations.from_axis_angle(np.array([1.0, 0, 0]), np.pi / 4)
    )
    poses = np.stack([sunk, on_edge])[:, None]  # [2 frames, 1 body, 7]
    np.testing.assert_allclose(metrics.floor_penetration(poses, [CUBE], floor_z)[:, 0], [0.01, 0.0], atol=1e-12)
    np.testing.assert_allclose(metrics.lowest_vertex_height(poses, [CUBE], floor_z)[:, 0], [-0.01, 0.003], atol=1e-12)


def test_configuration_error_broadcasts_over_a_candidate_axis_and_matches_a_loop():
    rng = np.random.default_rng(0)
    n_candidates, n_trajectories, n_frames, n_bodies = 4, 3, 5, 2
    widths = np.array([0.1, 0.25])
    true = np.concatenate(
        [
            rng.normal(size=(n_trajectories, n_frames, n_bodies, 3)),
            rotations.uniform_random(rng, n_trajectories * n_frames * n_bodies).reshape(
                n_trajectories, n_frames, n_bodies, 4
            ),
        ],
        axis=-1,
    )
    pred = np.concatenate(
        [
            rng.normal(size=(n_candidates, n_trajectories, n_frames, n_bodies, 3)),
            rotations.uniform_random(rng, n_candidates * n_trajectories * n_frames * n_bodies).reshape(
                n_candidates, n_trajectories, n_frames, n_bodies, 4
            ),
        ],
        axis=-1,
    )
    batched = metrics.configuration_error(true, pred, widths)
    assert batched.shape == (n_candidates, n_trajectories, n_frames)
    for b, n, t in itertools.product(range(n_candidates), range(n_trajectories), range(n_frames)):
        expected = 0.0
        for k in range(n_bodies):
            offset = true[n, t, k, :3] - pred[b, n, t, k, :3]
            # The angle from the rotation matrices, independent of the quaternion code under test.
            relative = rotations.to_matrix(true[n, t, k, 3:]).T @ rotations.to_matrix(pred[b, n, t, k, 3:])
            angle = np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1))
            expected += 2 / widths[k] * offset @ offset + angle**2
        assert batched[b, n, t] == pytest.approx(expected, rel=1e-9)


def test_shape_mismatches_name_the_shapes():
    with pytest.raises(ValueError, match=r"\(2, 3, 7\).*\(2, 4, 7\)"):
        metrics.configuration_error(np.zeros((2, 3, 7)), np.zeros((2, 4, 7)), np.ones(3))
    with pytest.raises(ValueError, match=r"widths \(2,\)"):
        metrics.position_error(np.zeros((5, 3, 7)), np.zeros((5, 3, 7)), np.ones(2))
    with pytest.raises(ValueError, match=r"\(1, 4, 1, 7\).*\(1, 5, 1, 7\)"):
        metrics.compute_metrics(np.zeros((1, 4, 1, 7)), np.zeros((1, 5, 1, 7)), [4], 1, [CUBE], 0.0)


# ---------------------------------------------------------------- separating-axis test


def test_aligned_cubes_overlapping_along_x_have_that_depth():
    depth = 0.013
    separation = metrics.pair_separation(pose([0, 0, 0]), pose([WIDTH - depth, 0.02, -0.01]), CUBE, CUBE)
    assert separation == pytest.approx(-depth, abs=1e-12)


def test_cubes_overlapping_diagonally_have_the_smaller_overlap_as_depth():
    separation = metrics.pair_separation(pose([0, 0, 0]), pose([WIDTH - 0.02, WIDTH - 0.005, 0.0]), CUBE, CUBE)
    assert separation == pytest.approx(-0.005, abs=1e-12)


def test_cube_turned_45_degrees_pressing_its_edge_into_a_face():
    edge_reach = WIDTH / np.sqrt(2)  # centre to vertical edge of the turned cube
    for depth in (0.0, 0.004):
        turned = pose([WIDTH / 2 + edge_reach - depth, 0.01, 0.0], about_z(np.pi / 4))
        assert metrics.pair_separation(pose([0, 0, 0]), turned, CUBE, CUBE) == pytest.approx(-depth, abs=1e-12)


def test_separated_cubes_give_the_face_gap_and_a_lower_bound_for_facing_corners():
    gap = metrics.pair_separation(pose([0, 0, 0]), pose([0.03, WIDTH + 0.007, 0.01]), CUBE, CUBE)
    assert gap == pytest.approx(0.007, abs=1e-12)
    # Corner to corner the true distance is hypot(0.004, 0.003); the best single axis sees only 0.004.
    corners = metrics.pair_separation(pose([0, 0, 0]), pose([WIDTH + 0.004, WIDTH + 0.003, 0.0]), CUBE, CUBE)
    assert corners == pytest.approx(0.004, abs=1e-12)
    assert corners < np.hypot(0.004, 0.003)


def test_pair_separation_broadcasts_and_matches_single_calls():
    frames = np.stack([pose([WIDTH - 0.01, 0, 0]), pose([WIDTH + 0.02, 0, 0])])
    batched = metrics.pair_separation(pose([0, 0, 0]), frames, CUBE, box([0.05, 0.05, 0.05]))
    assert batched.shape == (2,)
    np.testing.assert_allclose(batched, [-0.0076, 0.0224], atol=1e-12)


def _minkowski_depth(vertices_a: np.ndarray, vertices_b: np.ndarray) -> float:
    """Penetration depth as the origin's distance to the boundary of A − B (an independent, exact reference)."""
    hull = ConvexHull((vertices_a[:, None, :] - vertices_b[None, :, :]).reshape(-1, 3))
    offsets = hull.equations[:, 3]  # n·x + offset <= 0 inside, |n| = 1
    return float(-offsets.max()) if offsets.max() < 0 else 0.0


def test_sat_depth_equals_minkowski_reference_on_random_convex_pairs():
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(20000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    checked = 0
    for trial in range(40):
        scale_a, scale_b = rng.uniform(0.02, 0.08, size=(2, 3))
        shape_a = convex_mesh(rng.normal(size=(12, 3)) * scale_a) if trial % 2 else box(scale_a)
        shape_b = convex_mesh(rng.normal(size=(10, 3)) * scale_b) if trial % 2 else box(scale_b)
        pose_a = pose(rng.normal(scale=0.01, size=3), rotations.uniform_random(rng, 1)[0])
        pose_b = pose(rng.normal(scale=0.03, size=3), rotations.uniform_random(rng, 1)[0])
        world_a = world_vertices(pose_a, shape_a.vertices)
        world_b = world_vertices(pose_b, shape_b.vertices)
        reference = _minkowski_depth(world_a, world_b)
        if reference == 0.0:
            continue
        separation = metrics.pair_separation(pose_a, pose_b, shape_a, shape_b)
        assert -separation == pytest.approx(reference, abs=1e-10)
        sampled = world_a @ directions.T, world_b @ directions.T
        sampled_overlap = np.minimum(sampled[0].max(0) - sampled[1].min(0), sampled[1].max(0) - sampled[0].min(0)).min()
        assert -separation <= sampled_overlap + 1e-12
        checked += 1
    assert checked >= 20


def test_prefilter_does_not_change_depths_or_touches():
    rng = np.random.default_rng(2)
    meshes = [CUBE, solid(4), solid(20), box([0.02, 0.06, 0.03])]
    n_frames = 400
    spread = rng.uniform(0.02, 0.3, size=(n_frames, 1, 1))
    poses = np.concatenate(
        [
            rng.normal(size=(n_frames, 4, 3)) * spread,
            rotations.uniform_random(rng, n_frames * 4).reshape(n_frames, 4, 4),
        ],
        axis=-1,
    )
    geometries = [metrics.convex_geometry(mesh, k) for k, mesh in enumerate(meshes)]
    tolerance = 0.01
    filtered = metrics._pairwise_separations(poses, geometries, cutoff=tolerance)
    full = np.stack(
        [
            metrics.pair_separation(poses[:, a], poses[:, b], meshes[a], meshes[b])
            for a, b in itertools.combinations(range(4), 2)
        ],
        axis=-1,
    )
    skipped = np.isinf(filtered)
    assert 0 < skipped.sum() < skipped.size  # both branches are exercised
    np.testing.assert_allclose(filtered[~skipped], full[~skipped], rtol=0, atol=1e-15)
    assert np.all(full[skipped] > tolerance)
    depth = metrics.interbody_penetration(poses, meshes)
    assert depth.shape == (n_frames, 4, 4)
    first, second = np.array(list(itertools.combinations(range(4), 2))).T
    np.testing.assert_allclose(depth[:, first, second], np.maximum(0.0, -full), atol=1e-15)
    np.testing.assert_array_equal(depth, depth.transpose(0, 2, 1))


def test_non_convex_mesh_is_refused():
    notch = np.array([[0.1, 0.1, 0.3]])  # a point inside the tetrahedron, where its slanted face is dented to
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    hull = convex_mesh(points)
    top = np.flatnonzero(np.all(np.isin(hull.faces, [1, 2, 3]), axis=1))[0]
    a, b, c = hull.faces[top]
    faces = np.concatenate([np.delete(hull.faces, top, axis=0), [[a, b, 4], [b, c, 4], [c, a, 4]]])
    dented = Mesh(np.concatenate([hull.vertices, notch]), faces)
    with pytest.raises(ValueError, match="convex"):
        metrics.interbody_penetration(np.stack([pose([0, 0, 0]), pose([5, 0, 0])]), [dented, CUBE])


# ---------------------------------------------------------------- scoring protocol


def _three_cube_trajectory() -> np.ndarray:
    """Cubes in a row along x; 0 and 1 touch face to face at frame 2, 1 and 2 overlap by 3 mm at frame 4."""
    n_frames = 6
    poses = np.zeros((n_frames, 3, 7))
    poses[..., 3] = 1.0
    poses[:, 0, 0] = 0.0
    poses[:, 1, 0] = WIDTH + np.array([0.05, 0.02, 0.0, 0.02, 0.04, 0.05])
    poses[:, 2, 0] = poses[:, 1, 0] + WIDTH + np.array([0.05, 0.03, 0.02, 0.01, -0.003, 0.01])
    poses[..., 2] = WIDTH / 2 + 0.01
    return poses


def test_pairwise_collisions_count_distinct_touching_pairs_for_truth_and_prediction():
    true = _three_cube_trajectory()[None]
    apart = true.copy()
    apart[..., 0] *= 3.0  # the same motion, stretched so no pair ever touches
    result = metrics.compute_metrics(true, apart, [6], 1, [CUBE] * 3, floor_z=0.0)
    assert result.summary["pairwise_collisions_true"] == 2
    assert result.summary["pairwise_collisions"] == 0
    assert result.summary["interbody_penetration_m"] == pytest.approx(0.0)
    exact = metrics.compute_metrics(true, true, [6], 1, [CUBE] * 3, floor_z=0.0)
    assert exact.summary["pairwise_collisions"] == 2
    np.testing.assert_allclose(exact.per_frame["interbody_penetration_m"], [np.nan, 0, 0, 0, 0.003, 0], atol=1e-12)
    assert exact.summary["interbody_penetration_m"] == pytest.approx(0.003 / 5)
    # Scoring from frame 3 on leaves only the 1-2 contact.
    assert metrics.compute_metrics(true, true, [6], 3, [CUBE] * 3, 0.0).summary["pairwise_collisions"] == 1


def _two_tosses(n_frames: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two single-cube tosses of 6 and 12 frames; predictions off by half and a tenth of the width, NaN past the end."""
    true = np.zeros((2, n_frames, 1, 7))
    true[..., 2] = 0.2
    true[..., 3] = 1.0
    pred = true.copy()
    pred[0, :, 0, 0] += 0.5 * WIDTH
    pred[1, :, 0, 0] += 0.1 * WIDTH
    lengths = np.array([6, 12])
    true[0, 6:] = np.nan
    pred[0, 6:] = np.nan
    return true, pred, lengths


def test_summary_is_the_mean_of_trajectory_means_and_frames_past_the_length_are_ignored():
    true, pred, lengths = _two_tosses()
    result = metrics.compute_metrics(true, pred, lengths, 2, [CUBE], floor_z=0.0)
    np.testing.assert_allclose(result.per_trajectory["pos_err"], [0.5, 0.1])
    assert result.summary["pos_err"] == pytest.approx(0.3)  # frame-weighted it would be (4*0.5 + 10*0.1)/14
    assert result.summary["scored_frames"] == 14
    assert result.summary["rot_err_rad"] == pytest.approx(0.0)
    assert result.summary["min_vertex_height_m"] == pytest.approx(0.2 - WIDTH / 2)
    assert result.summary["floor_penetration_m"] == 0.0
    assert result.summary["interbody_penetration_m"] is None
    assert result.summary["pairwise_collisions"] is None and result.summary["pairwise_collisions_true"] is None
    assert "interbody_penetration_m" not in result.per_frame
    np.testing.assert_array_equal(result.per_frame["n_trajectories"], [0, 0, 2, 2, 2, 2, 1, 1, 1, 1, 1, 1])
    curve = result.per_frame["pos_err"]
    assert np.all(np.isnan(curve[:2]))
    np.testing.assert_allclose(curve[2:6], 0.3)
    np.testing.assert_allclose(curve[6:], 0.1)
    np.testing.assert_array_equal(result.per_trajectory["length"], [6, 12])


def test_the_recordings_own_floor_penetration_is_scored_beside_the_predictions():
    true, pred, lengths = _two_tosses()
    true[1, 2:, 0, 2] = WIDTH / 2 - 0.004  # the recorded cube sits 4 mm inside the floor, the prediction on it
    pred[1, :, 0, 2] = WIDTH / 2
    result = metrics.compute_metrics(true, pred, lengths, 2, [CUBE], floor_z=0.0)
    np.testing.assert_allclose(result.per_trajectory["floor_penetration_true_m"], [0.0, 0.004])
    assert result.summary["floor_penetration_true_m"] == pytest.approx(0.002)
    assert result.summary["floor_penetration_m"] == pytest.approx(0.0)
    itself = metrics.compute_metrics(true, true, lengths, 2, [CUBE], floor_z=0.0)
    assert itself.summary["floor_penetration_m"] == itself.summary["floor_penetration_true_m"]


def test_non_finite_prediction_inside_the_scored_frames_is_not_dropped():
    true, pred, lengths = _two_tosses()
    pred[1, 7, 0, 0] = np.nan
    result = metrics.compute_metrics(true, pred, lengths, 2, [CUBE], floor_z=0.0)
    assert result.per_trajectory["pos_err"][0] == pytest.approx(0.5)
    assert np.isnan(result.per_trajectory["pos_err"][1])
    assert np.isnan(result.summary["pos_err"]) and np.isnan(result.summary["rot_err_rad"])
    assert np.isnan(result.summary["floor_penetration_m"]) and np.isnan(result.summary["min_vertex_height_m"])
    assert np.isnan(result.per_frame["pos_err"][7]) and result.per_frame["pos_err"][6] == pytest.approx(0.1)

    three = _three_cube_trajectory()[None]
    diverged = three.copy()
    diverged[0, 4, 2, :3] = np.inf
    result = metrics.compute_metrics(three, diverged, [6], 1, [CUBE] * 3, floor_z=0.0)
    assert np.isnan(result.summary["pairwise_collisions"])
    assert result.summary["pairwise_collisions_true"] == 2
    assert not np.isfinite(result.summary["interbody_penetration_m"])


def test_scoring_protocol_rejects_bad_lengths():
    true, pred, lengths = _two_tosses()
    with pytest.raises(ValueError, match="trajectory 0 has length 6 <= start_frame 6"):
        metrics.compute_metrics(true, pred, lengths, 6, [CUBE], 0.0)
    with pytest.raises(ValueError, match="length 13"):
        metrics.compute_metrics(true, pred, [6, 13], 2, [CUBE], 0.0)
    with pytest.raises(ValueError, match="2 meshes"):
        metrics.compute_metrics(true, pred, lengths, 2, [CUBE, CUBE], 0.0)


def test_the_protocol_scores_frames_after_the_context_and_weighs_every_trajectory_once():
    from contactbench.protocol import scored_frames, trajectory_means

    scored = scored_frames(np.array([10, 7]), horizon=10, context_frames=6)
    assert scored.sum(axis=1).tolist() == [4, 1] and not scored[:, :6].any() and not scored[1, 7:].any()
    values = np.where(np.arange(10) < 8, 1.0, 3.0)[None, :].repeat(2, axis=0)  # frames 8, 9 of the long one cost 3
    values[1, 7:] = np.nan  # past a trajectory's end nothing counts, whatever is there
    np.testing.assert_allclose(trajectory_means(values, scored), [2.0, 1.0])
