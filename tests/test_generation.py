"""Tests of the PyBullet benchmark generator: solids, initial states, engine physics, datasets and determinism."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pybullet
import pytest

from contactbench import rotations
from contactbench.generation.bullet import CONTACT_KEYS, BulletScene
from contactbench.generation.generator import derive_seed, generate_dataset, toss_chunks, toss_rng
from contactbench.generation.scenes import SceneSpec, SpawnError, sample_initial_state
from contactbench.generation.solids import SOLID_NAMES, WIDTH, convex_mesh, solid
from contactbench.kinematics import estimate_velocities, world_vertices
from contactbench.meshes import closedness_problem
from contactbench.recordings import read_recordings
from contactbench.sim.bullet_world import BulletSettings, recorded_motion

SETTINGS = BulletSettings()
CUBE = solid(6)
SMALL_SPLITS = {"train": 3, "val": 2, "test": 2}


def cube_scene(bodies: int = 1, friction: float = 0.5, restitution: float = 0.0) -> BulletScene:
    return BulletScene(CUBE, SceneSpec("test", friction, restitution, bodies=bodies), SETTINGS)


def at_rest(position, orientation=(1.0, 0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    return np.array([[*position, *orientation]]), np.zeros((1, 6))


# ---------------------------------------------------------------- solids


@pytest.mark.parametrize("faces", sorted(SOLID_NAMES))
def test_solid_is_closed_centred_isotropic_and_has_its_face_count(faces):
    mesh = solid(faces)
    assert closedness_problem(mesh.faces, len(mesh.vertices)) is None
    assert mesh.width == pytest.approx(WIDTH, abs=1e-15)
    com, inertia = mesh.mass_properties(SETTINGS.mass)
    assert np.abs(com).max() < 1e-15
    assert np.abs(inertia - inertia[0, 0] * np.eye(3)).max() < 1e-12 * inertia[0, 0]
    v0, v1, v2 = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    normals = np.cross(v1 - v0, v2 - v0)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # Outward winding: every triangle of a convex solid centred at the origin faces away from the origin.
    assert np.all(np.einsum("ij,ij->i", normals, v0 + v1 + v2) > 0)
    planes = np.unique(np.round(normals, 9), axis=0)
    assert len(planes) == faces


def test_cube_inertia_matches_the_closed_form():
    _, inertia = CUBE.mass_properties(SETTINGS.mass)
    np.testing.assert_allclose(np.diag(inertia), SETTINGS.mass * WIDTH**2 / 6, rtol=1e-12)


# ---------------------------------------------------------------- initial states


def test_scene_spec_normalises_hydra_style_values():
    spec = SceneSpec("multicubes", friction=0, restitution=1, bodies=3.0, position_low=[-0.4, -0.4, 0.13])
    assert spec.friction == 0.0 and isinstance(spec.friction, float)
    assert spec.position_low == (-0.4, -0.4, 0.13)
    assert spec.bodies == 3
    hash(spec)


def test_single_body_state_follows_table_2b():
    spec = SceneSpec("frictioncubes", 0.5, 0.0)
    rng = np.random.default_rng(0)
    states = [sample_initial_state(spec, CUBE, rng) for _ in range(200)]
    poses = np.concatenate([pose for pose, _ in states])
    velocities = np.concatenate([velocity for _, velocity in states])
    assert np.all(poses[:, :3] >= spec.position_low) and np.all(poses[:, :3] <= spec.position_high)
    np.testing.assert_allclose(np.linalg.norm(poses[:, 3:], axis=1), 1.0, atol=1e-12)
    assert np.all(np.abs(velocities[:, :2]) <= 1.2) and np.abs(velocities[:, :2]).max() > 1.0
    assert np.all(velocities[:, 2:] == 0.0)


def _boxes(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    vertices = world_vertices(poses, CUBE.vertices)
    return vertices.min(axis=1), vertices.max(axis=1)


def test_multi_body_spawn_has_no_overlapping_boxes_and_stays_in_the_region():
    spec = SceneSpec("multicubes", 0.18, 0.125, bodies=5, center_bias_speed=0.5)
    rng = np.random.default_rng(1)
    for _ in range(50):
        poses, _ = sample_initial_state(spec, CUBE, rng)
        low, high = _boxes(poses)
        assert np.all(low[:, :2] >= np.array(spec.position_low[:2]) - 1e-12)
        assert np.all(high[:, :2] <= np.array(spec.position_high[:2]) + 1e-12)
        assert np.all((poses[:, 2] >= 0.13) & (poses[:, 2] <= 0.15))
        for a, b in itertools.combinations(range(5), 2):
            assert np.any((high[a] <= low[b]) | (high[b] <= low[a])), f"bodies {a} and {b} overlap"


def test_velocity_bias_points_to_the_centre():
    spec = SceneSpec(
        "multicubes", 0.18, 0.125, bodies=4, center_bias_speed=0.5, velocity_low=(0, 0, 0), velocity_high=(0, 0, 0)
    )
    poses, velocities = sample_initial_state(spec, CUBE, np.random.default_rng(2))
    direction = poses[:, :2] / np.linalg.norm(poses[:, :2], axis=1, keepdims=True)
    np.testing.assert_allclose(velocities[:, :2], -0.5 * direction, atol=1e-15)
    assert np.all(velocities[:, 2:] == 0.0)


def test_spawn_error_names_the_body_and_the_attempts():
    spec = SceneSpec("multicubes", 0.18, 0.125, bodies=40)
    with pytest.raises(SpawnError, match=r"body \d+ of 40 .* 100 attempts"):
        sample_initial_state(spec, CUBE, np.random.default_rng(0))


# ---------------------------------------------------------------- engine physics


def test_free_flight_falls_at_g_and_conserves_angular_momentum():
    # A flat box (distinct principal moments) so the body-frame spin really changes while momentum must not.
    box = convex_mesh(np.array(list(itertools.product((-0.05, 0.05), (-0.03, 0.03), (-0.015, 0.015)))))
    spec = SceneSpec("free", 0.5, 0.0)
    orientation = rotations.from_axis_angle(np.array([1.0, 2.0, 3.0]), 0.7)
    poses0 = np.array([[0.1, -0.2, 2.0, *orientation]])
    velocities0 = np.array([[0.3, -0.2, 1.0, 3.0, -2.0, 5.0]])
    with BulletScene(box, spec, SETTINGS) as scene:
        poses, velocities = scene.simulate(poses0, velocities0, 40)
    times = np.arange(40) * SETTINGS.dt
    acceleration = [2 * np.polyfit(times, poses[:, 0, axis], 2)[0] for axis in range(3)]
    np.testing.assert_allclose(acceleration, SETTINGS.gravity, atol=1e-6)
    _, inertia = box.mass_properties(SETTINGS.mass)
    rotation = rotations.to_matrix(poses[:, 0, 3:])
    omega = velocities[:, 0, 3:]
    momentum = np.einsum("tij,jk,tlk,tl->ti", rotation, inertia, rotation, omega)
    assert np.abs(momentum - momentum[0]).max() < 0.02 * np.linalg.norm(momentum[0])
    assert np.abs(omega - omega[0]).max() > 0.1 * np.linalg.norm(omega[0])  # the check above is not trivial


def test_no_air_drag_on_objects():
    poses0, velocities0 = at_rest((0.0, 0.0, 2.0))
    velocities0[0] = [0.3, -0.2, 1.0, 3.0, -2.0, 5.0]
    with cube_scene() as scene:
        info = pybullet.getDynamicsInfo(scene.bodies[0], -1, physicsClientId=scene.client)
        mass, friction, inertia, restitution, rolling, spinning, margin = (
            info[0],
            info[1],
            info[2],
            info[5],
            info[6],
            info[7],
            info[11],
        )
        assert (mass, friction, restitution, rolling, spinning, margin) == (0.37, 0.5, 0.0, 0.0, 0.0, 0.0)
        np.testing.assert_allclose(inertia, scene.inertia_diagonal, rtol=1e-12)
        _, velocities = scene.simulate(poses0, velocities0, 30)
        # getDynamicsInfo does not report damping; motion does: an isotropic body in free flight keeps its
        # horizontal velocity and its spin exactly.
        drift = np.abs(velocities[:, 0, [0, 1, 3, 4, 5]] - velocities0[0, [0, 1, 3, 4, 5]]).max()
        assert drift < 1e-12
        pybullet.changeDynamics(
            scene.bodies[0], -1, linearDamping=0.04, angularDamping=0.04, physicsClientId=scene.client
        )
        _, damped = scene.simulate(poses0, velocities0, 30)
        assert np.abs(damped[:, 0, [0, 1, 3, 4, 5]] - velocities0[0, [0, 1, 3, 4, 5]]).max() > 1e-4


def test_cube_resting_on_the_floor_stays_put():
    half = WIDTH / 2
    with cube_scene(friction=0.5, restitution=0.0) as scene:
        poses, velocities = scene.simulate(*at_rest((0.1, -0.2, half)), SETTINGS.frames)
    vertices = world_vertices(poses[:, 0], CUBE.vertices)
    assert vertices[..., 2].min() >= -1e-3
    assert np.abs(poses[:, 0, :2] - [0.1, -0.2]).max() < 5e-4
    # The first step finds a single floor contact and tips the cube by a few mrad before it settles back.
    tilt = rotations.angle_between(poses[:, 0, 3:], poses[0, 0, 3:])
    assert tilt.max() < 1e-2 and tilt[-1] < 1e-4
    # PyBullet's default 1 mm collision margin would leave the cube hovering 1 mm high.
    assert abs(poses[-1, 0, 2] - half) < 2e-4
    assert np.abs(velocities[-1]).max() < 1e-3


def test_recorded_quaternions_are_w_first():
    orientation = rotations.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.pi / 2)
    np.testing.assert_allclose(orientation, [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])
    poses0, velocities0 = at_rest((0.0, 0.0, 2.0), orientation)
    velocities0[0, 3:] = [1.0, -2.0, 0.5]
    with cube_scene() as scene:
        poses, velocities = scene.simulate(poses0, velocities0, 10)
        _, engine_xyzw = pybullet.getBasePositionAndOrientation(scene.bodies[0], physicsClientId=scene.client)
    np.testing.assert_allclose(poses[0, 0, 3:], orientation, atol=1e-15)
    engine_wxyz = np.array(engine_xyzw)[[3, 0, 1, 2]]
    # Either sign is the same orientation; the recording keeps the quaternion path continuous.
    assert np.array_equal(poses[-1, 0, 3:], engine_wxyz) or np.array_equal(poses[-1, 0, 3:], -engine_wxyz)
    # The recorded (world-frame) spin is what the recorded quaternions do between frames.
    np.testing.assert_allclose(estimate_velocities(poses, SETTINGS.dt)[1:], velocities[1:], atol=1e-9)


def test_recorded_motion_reorders_quaternions_and_makes_their_signs_continuous():
    # PyBullet's x, y, z, w quaternions with the sign flipping at frames 1 and 3; velocities pass through untouched.
    q_xyzw = rotations.normalize(np.array([0.1, 0.2, 0.3, 0.9]))
    signs = np.array([1.0, -1.0, -1.0, 1.0])
    states = np.zeros((2, 4, 1, 13))  # two tosses at once
    states[..., :3] = [0.5, -0.5, 0.25]
    states[..., 3:7] = signs[None, :, None, None] * q_xyzw
    states[..., 7:] = np.arange(6.0)
    q_wxyz = q_xyzw[[3, 0, 1, 2]]
    initial = np.stack([q_wxyz, -q_wxyz])[:, None]  # the second toss starts on the other side
    poses, velocities = recorded_motion(states, initial)
    assert poses.shape == (2, 4, 1, 7) and velocities.shape == (2, 4, 1, 6)
    np.testing.assert_array_equal(poses[0, :, 0, 3:], np.tile(q_wxyz, (4, 1)))
    np.testing.assert_array_equal(poses[1, :, 0, 3:], np.tile(-q_wxyz, (4, 1)))
    np.testing.assert_array_equal(poses[..., :3], states[..., :3])
    np.testing.assert_array_equal(velocities, states[..., 7:])


def test_batched_conversion_of_raw_tosses_equals_simulate():
    spec = SceneSpec("multicubes", 0.18, 0.125, bodies=2, center_bias_speed=0.5)
    initial = [sample_initial_state(spec, CUBE, np.random.default_rng(seed)) for seed in range(2)]
    with cube_scene(bodies=2, friction=0.18, restitution=0.125) as scene:
        raw = np.stack([scene.toss(poses, velocities, 60)[0] for poses, velocities in initial])
        one_by_one = [scene.simulate(poses, velocities, 60) for poses, velocities in initial]
    poses, velocities = recorded_motion(raw, np.stack([poses[:, 3:] for poses, _ in initial]))
    for n, (expected_poses, expected_velocities) in enumerate(one_by_one):
        np.testing.assert_array_equal(poses[n], expected_poses)
        np.testing.assert_array_equal(velocities[n], expected_velocities)
    assert np.abs(velocities[:, -1] - velocities[:, 0]).max() > 0.1  # the tosses moved: the check is not trivial


def test_contact_wrenches_explain_the_motion():
    # Two cubes sliding into each other on the floor: floor and body-body contacts, normal and friction parts.
    poses0 = np.array([[-0.12, 0.0, WIDTH / 2, 1.0, 0.0, 0.0, 0.0], [0.12, 0.01, WIDTH / 2, 1.0, 0.0, 0.0, 0.0]])
    velocities0 = np.array([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    with cube_scene(bodies=2, friction=0.3, restitution=0.5) as scene:
        _, velocities, contacts = scene.simulate(poses0, velocities0, 40, record_contacts=True)
    assert set(contacts) == set(CONTACT_KEYS) and all(c.shape == (40, 2, 3) for c in contacts.values())
    assert all(np.all(c[0] == 0.0) for c in contacts.values())
    force = contacts["contact_normal_force"] + contacts["contact_friction_force"]
    torque = contacts["contact_normal_torque"] + contacts["contact_friction_torque"]
    momentum_change = SETTINGS.mass * np.diff(velocities[..., :3], axis=0) / SETTINGS.dt
    np.testing.assert_allclose(momentum_change, SETTINGS.mass * np.array(SETTINGS.gravity) + force[1:], atol=1e-9)
    inertia = np.diag(CUBE.mass_properties(SETTINGS.mass)[1])[0]  # isotropic: no gyroscopic term
    np.testing.assert_allclose(inertia * np.diff(velocities[..., 3:], axis=0) / SETTINGS.dt, torque[1:], atol=1e-9)
    assert np.abs(contacts["contact_normal_force"][..., 0]).max() > 1.0  # the cubes did push each other
    assert np.abs(contacts["contact_friction_force"]).max() > 0.1


def test_a_toss_does_not_depend_on_the_tosses_before_it():
    # Hardest case: the second toss starts exactly where the first ended, resting cubes in contact, where a
    # leftover contact manifold would warm-start the solver.
    start = np.array(
        [
            [0.0, 0.0, 0.06, 1.0, 0.0, 0.0, 0.0],
            [WIDTH, 0.0, 0.06, 1.0, 0.0, 0.0, 0.0],
            [0.05, 0.0, 0.17, 0.9, 0.1, 0.3, 0.2],
        ]
    )
    start[:, 3:] = rotations.normalize(start[:, 3:])
    with cube_scene(bodies=3) as scene:
        poses, velocities = scene.simulate(start, np.zeros((3, 6)), 60)
        after_history = scene.simulate(poses[-1], velocities[-1], 20)
    with cube_scene(bodies=3) as fresh_scene:
        fresh = fresh_scene.simulate(poses[-1], velocities[-1], 20)
    np.testing.assert_array_equal(after_history[0], fresh[0])
    np.testing.assert_array_equal(after_history[1], fresh[1])


# ---------------------------------------------------------------- datasets


def _generate(path: Path, spec: SceneSpec, **kwargs) -> Path:
    options = dict(settings=BulletSettings(frames=40), split_sizes=SMALL_SPLITS, workers=1, progress=False)
    options.update(kwargs)
    return generate_dataset(spec, path, **options)


def _file_bytes(root: Path) -> dict[str, bytes]:
    return {str(path.relative_to(root)): path.read_bytes() for path in sorted(root.rglob("*")) if path.is_file()}


def test_dataset_layout_splits_and_initial_states(tmp_path):
    spec = SceneSpec("multicubes", 0.18, 0.125, bodies=2, center_bias_speed=0.5)
    root = _generate(tmp_path / "data", spec, variant="bodies=2", seed=7, record_contacts=True)
    recordings = read_recordings(root)
    assert recordings.name == "multicubes-bodies=2"
    assert recordings.dt == SETTINGS.dt and recordings.floor_z == 0.0
    np.testing.assert_array_equal(recordings.gravity, SETTINGS.gravity)
    assert [body.name for body in recordings.bodies] == ["cube_0", "cube_1"]
    assert all(body.mass == 0.37 and body.mesh == "meshes/cube.obj" for body in recordings.bodies)
    np.testing.assert_allclose(recordings.bodies[0].inertia_diagonal, SETTINGS.mass * WIDTH**2 / 6, rtol=1e-12)
    np.testing.assert_allclose(recordings.body_mesh(0).vertices, CUBE.vertices)
    generator = recordings.meta["generator"]
    assert (
        generator["engine"] == "pybullet"
        and generator["seed"] == 7
        and generator["derived_seed"] == derive_seed(7, spec)
    )
    assert generator["scene"]["bodies"] == 2 and generator["settings"]["frames"] == 40 and generator["solid"] == "cube"
    toss = 0
    for name, size in SMALL_SPLITS.items():
        split = recordings.split(name)
        assert split.poses.shape == (size, 40, 2, 7) and split.velocities.shape == (size, 40, 2, 6)
        assert np.all(split.lengths == 40)
        assert all(split.extras[key].shape == (size, 40, 2, 3) for key in CONTACT_KEYS)
        quaternions = split.poses[..., 3:]
        assert np.all(np.einsum("ntkq,ntkq->ntk", quaternions[:, 1:], quaternions[:, :-1]) > 0)
        for n in range(size):
            # Toss numbering runs across the splits in order: train 0-2, val 3-4, test 5-6.
            poses0, velocities0 = sample_initial_state(spec, CUBE, toss_rng(derive_seed(7, spec), toss))
            np.testing.assert_allclose(split.poses[n, 0], poses0, atol=1e-15)
            np.testing.assert_allclose(split.velocities[n, 0], velocities0, atol=1e-15)
            toss += 1


def test_generation_is_byte_deterministic_and_independent_of_workers(tmp_path):
    spec = SceneSpec("frictioncubes", 0.25, 0.0)
    first = _file_bytes(_generate(tmp_path / "a", spec, seed=3))
    assert first == _file_bytes(_generate(tmp_path / "b", spec, seed=3))
    assert first == _file_bytes(_generate(tmp_path / "c", spec, seed=3, workers=2))
    other_seed = _file_bytes(_generate(tmp_path / "d", spec, seed=4))
    assert other_seed["train.npz"] != first["train.npz"]
    other_variant = _file_bytes(_generate(tmp_path / "e", SceneSpec("frictioncubes", 0.5, 0.0), seed=3))
    assert other_variant["train.npz"] != first["train.npz"]


def test_generation_reports_the_toss_that_cannot_be_placed(tmp_path):
    with pytest.raises(SpawnError, match=r"toss 0 \(train toss 0\): body \d+ of 40"):
        _generate(tmp_path / "crowded", SceneSpec("multicubes", 0.18, 0.125, bodies=40))
    assert not (tmp_path / "crowded").exists()


@pytest.mark.parametrize("total, workers", [(550, 2), (550, 1), (7, 2), (1, 2)])
def test_toss_chunks_cover_every_toss_once_and_shrink_toward_the_end(total, workers):
    chunks = toss_chunks(total, workers)
    assert [toss for chunk in chunks for toss in chunk] == list(range(total))
    sizes = [len(chunk) for chunk in chunks]
    assert max(sizes) <= 32 and sizes == sorted(sizes, reverse=True) and sizes[-1] == 1


def test_a_failing_worker_fails_the_whole_generation(tmp_path):
    with pytest.raises(SpawnError, match=r"toss \d+ \((train|val|test) toss \d+\): body \d+ of 40"):
        _generate(tmp_path / "crowded", SceneSpec("multicubes", 0.18, 0.125, bodies=40), workers=2)
    assert not (tmp_path / "crowded").exists()
