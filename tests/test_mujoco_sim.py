"""MuJoCo scene building and batched rollouts checked against closed-form physics and the recordings conventions."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import mujoco
import numpy as np
import pytest

from contactbench import rotations
from contactbench.kinematics import world_vertices
from contactbench.meshes import Mesh
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.scene import Recordings, Split
from contactbench.sim.mujoco_scene import ContactParameters, SceneEffects, build_model, pack_state, unpack_state
from contactbench.sim.rollout import MujocoRollouts, mechanical_energy, rollout_context

CUBE_DATA = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"
GRAVITY = np.array([0.0, 0.0, -9.81])
BOX_FACES = np.array(
    [
        [0, 3, 2],
        [0, 1, 3],
        [4, 7, 5],
        [4, 6, 7],
        [0, 5, 1],
        [0, 4, 5],
        [2, 7, 6],
        [2, 3, 7],
        [0, 6, 4],
        [0, 2, 6],
        [1, 7, 3],
        [1, 5, 7],
    ]
)  # corner index 4x + 2y + z; counter-clockwise seen from outside


def box(lower, upper) -> Mesh:
    """Axis-aligned box between corners `lower` and `upper` in its mesh frame (outward faces)."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    return Mesh(np.asarray(lower) + corners * (np.asarray(upper) - np.asarray(lower)), BOX_FACES)


def scene(
    meshes: list[Mesh],
    masses: list[float] | None = None,
    inertia_diagonals: list | None = None,
    dt: float = 0.01,
    gravity=GRAVITY,
    floor_z: float = 0.0,
) -> Recordings:
    """An in-memory recordings scene with one body per mesh and a one-frame split."""
    bodies = []
    for k in range(len(meshes)):
        body = {"name": f"body{k}", "mesh": f"meshes/body{k}.obj", "mass": 0.37 if masses is None else masses[k]}
        if inertia_diagonals is not None and inertia_diagonals[k] is not None:
            body["inertia_diagonal"] = list(inertia_diagonals[k])
        bodies.append(body)
    meta = {
        "format": "rigid-contact-recordings",
        "version": 1,
        "name": "test-scene",
        "dt": dt,
        "gravity": list(map(float, gravity)),
        "floor_z": floor_z,
        "bodies": bodies,
        "splits": {"train": "train.npz"},
    }
    poses = np.zeros((1, 1, len(meshes), 7))
    poses[..., 3] = 1.0
    meshes_by_path = {b["mesh"]: m for b, m in zip(bodies, meshes)}
    return Recordings(meta=meta, meshes=meshes_by_path, splits={"train": Split(poses, np.array([1]))})


CUBE = box([-0.05] * 3, [0.05] * 3)


def rest_pose(x: float = 0.0, y: float = 0.0, half: float = 0.05) -> np.ndarray:
    return np.array([x, y, half, 1.0, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def cube_data() -> Recordings:
    return read_recordings(CUBE_DATA, splits=["test"])


def test_free_flight_follows_semi_implicit_euler_and_g():
    dt, substeps, n_steps = 0.01, 3, 60
    simulator = MujocoRollouts(scene([CUBE], dt=dt), nthread=1, substeps=substeps)
    start = np.array([[[0.2, -0.1, 30.0, 1.0, 0.0, 0.0, 0.0]]])
    velocity = np.array([[[0.7, -0.3, 2.0, 0.0, 0.0, 0.0]]])
    result = simulator.simulate(ContactParameters.mujoco_default(1), start, velocity, n_steps)
    positions = result.poses[0, 0, :, 0, :3]
    h = dt / substeps
    steps = substeps * np.arange(1, n_steps + 1)[:, None]
    # v_n = v_0 + n h g, x_n = x_0 + h (v_1 + ... + v_n)
    expected = start[0, 0, :3] + steps * h * velocity[0, 0, :3] + h * h * GRAVITY * steps * (steps + 1) / 2
    np.testing.assert_allclose(positions, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.velocities[0, 0, :, 0, :3], velocity[0, 0, :3] + steps * h * GRAVITY, atol=1e-12)
    times = dt * np.arange(1, n_steps + 1)
    fitted_acceleration = 2 * np.polyfit(times, positions, 2)[0]
    np.testing.assert_allclose(fitted_acceleration, GRAVITY, rtol=0, atol=1e-9)
    assert not result.unstable.any()


def test_mechanical_energy_drops_by_the_semi_implicit_euler_loss_in_spinning_free_flight():
    dt = 0.01
    # Isotropic inertia: a spin about any axis stays steady, so only gravity changes the energy.
    data = scene([CUBE], inertia_diagonals=[(6e-4,) * 3], dt=dt)
    start = np.array([[[0.0, 0.0, 30.0, 1.0, 0.0, 0.0, 0.0]]])
    velocity = np.array([[[0.5, 0.0, 1.0, 3.0, -1.0, 2.0]]])
    result = MujocoRollouts(data, nthread=1).simulate(ContactParameters.mujoco_default(1), start, velocity, 50)
    energy = mechanical_energy(data, result.poses[0, 0], result.velocities[0, 0])
    initial = 0.5 * 0.37 * (0.5**2 + 1.0**2) + 0.5 * 6e-4 * 14.0 + 0.37 * 9.81 * 30.0
    np.testing.assert_allclose(mechanical_energy(data, start[0], velocity[0]), initial, rtol=1e-12)
    # Each step x += h v_new loses exactly m g^2 h^2 / 2 of kinetic + potential energy.
    loss_per_step = 0.5 * 0.37 * 9.81**2 * dt**2
    np.testing.assert_allclose(energy, initial - loss_per_step * np.arange(1, 51), rtol=1e-10)


def test_energy_of_a_candidate_scene_uses_its_own_centre_of_mass_and_gravity():
    # An offset centre of mass and a scaled gravity (diagnose.py's com_offset, gravity_scale): the energy of the
    # simulated scene is conserved up to the integrator's small loss only when measured with the scene's own mass
    # properties; with the recordings' ones it swings by the spin about the offset (such a swing once flagged correct
    # candidates as blown up).
    data = scene([CUBE], inertia_diagonals=[(6e-4,) * 3], dt=0.002)
    effects = SceneEffects(com_offset=(0.03, -0.02, 0.0), gravity_scale=0.9)
    params = dataclasses.replace(ContactParameters.mujoco_default(1), effects=effects)
    start = np.array([[[0.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0]]])
    velocity = np.array([[[0.5, 0.0, 1.0, 20.0, -10.0, 15.0]]])
    result = MujocoRollouts(data, nthread=1).simulate(params, start, velocity, 60)
    assert not result.unstable.any()
    own = mechanical_energy(data, result.poses[0, 0], result.velocities[0, 0], effects)
    initial = mechanical_energy(data, start[0], velocity[0], effects)
    np.testing.assert_allclose(own, initial, rtol=2e-3)
    assert np.all(own <= initial + 1e-9)  # no energy from nowhere
    recordings_view = mechanical_energy(data, result.poses[0, 0], result.velocities[0, 0])
    assert np.ptp(recordings_view) > 10 * np.ptp(own)


def test_resting_cube_stays_put(cube_data):
    half = cube_data.body_mesh(0).width / 2
    simulator = MujocoRollouts(cube_data, nthread=1)
    start = rest_pose(0.1, -0.2, half)[None, None]
    result = simulator.simulate(ContactParameters.mujoco_default(1), start, np.zeros((1, 1, 6)), 148)  # 1 s
    poses = result.poses[0, 0, :, 0]
    lowest = world_vertices(poses, cube_data.body_mesh(0).vertices)[..., 2].min(axis=-1)
    # Measured: 1.1e-5 m drift, 3.1e-4 rad tilt, 0.22 mm penetration (MuJoCo's soft contact rocks a resting box
    # on its 3 plane contacts in a tiny 4-step cycle).
    assert np.abs(poses[:, :2] - start[0, 0, :2]).max() < 1e-4
    assert rotations.angle_between(poses[:, 3:], start[0, 0, 3:]).max() < 1e-3
    assert 0 < -lowest.max() and -lowest.min() < 5e-4
    assert not result.unstable.any()


def test_drop_and_bounce_never_gains_energy():
    data = scene([CUBE], dt=1 / 148)
    tilt = rotations.from_axis_angle(np.array([1.0, 0.5, 0.0]), 0.6)
    start = np.concatenate([[0.0, 0.0, 0.3], tilt])[None, None]
    velocity = np.array([[[0.4, 0.0, -0.5, 0.0, 0.0, 4.0]]])
    params = [
        ContactParameters((0.5,), 0.5, stiffness, damping)
        for stiffness, damping in [(1e3, 10.0), (1e4, 50.0), (3e2, 5.0)]
    ]
    result = MujocoRollouts(data, nthread=1).simulate(params, start, velocity, 300)
    energy = mechanical_energy(data, result.poses[:, 0], result.velocities[:, 0])
    initial = mechanical_energy(data, start[0], velocity[0])
    assert np.all(energy <= initial + 1e-9)
    assert np.all(energy[:, -1] < 0.5 * initial)  # the bounces dissipated most of it
    assert (result.poses[:, 0, :, 0, 2] < 0.1).any(axis=-1).all()  # it did reach the floor
    assert not result.unstable.any()


def test_pack_unpack_round_trip():
    rng = np.random.default_rng(0)
    poses = np.concatenate([rng.normal(size=(5, 3, 3)), rotations.uniform_random(rng, 15).reshape(5, 3, 4)], axis=-1)
    velocities = rng.normal(size=(5, 3, 6))
    qpos, qvel = pack_state(poses, velocities)
    assert qpos.shape == (5, 21) and qvel.shape == (5, 18)
    # MuJoCo's free joint wants body-frame angular velocity: R^T omega_world.
    np.testing.assert_allclose(
        qvel.reshape(5, 3, 6)[..., 3:],
        np.einsum("nkji,nkj->nki", rotations.to_matrix(poses[..., 3:]), velocities[..., 3:]),
        atol=1e-12,
    )
    back_poses, back_velocities = unpack_state(qpos, qvel)
    np.testing.assert_allclose(back_poses, poses, atol=1e-12)
    np.testing.assert_allclose(back_velocities, velocities, atol=1e-12)


def test_spin_about_world_axis_with_offset_centre_of_mass():
    dt, n_steps = 0.002, 250
    mesh = box([0.03, -0.01, 0.02], [0.13, 0.05, 0.08])  # CoM (0.08, 0.02, 0.05), far from the mesh origin
    data = scene([mesh], inertia_diagonals=[(5e-4,) * 3], dt=dt, gravity=(0.0, 0.0, 0.0))
    com_body, _ = data.inertial(0)
    q0 = rotations.from_axis_angle(np.array([0.3, -1.0, 0.4]), 1.1)
    omega = 2.0 * np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    origin = np.array([0.5, -0.3, 1.0])
    com_world = origin + rotations.rotate(q0, com_body)
    # The centre of mass rests, so the mesh-frame origin moves at omega x (origin - com).
    start_velocity = np.concatenate([np.cross(omega, origin - com_world), omega])
    result = MujocoRollouts(data, nthread=1).simulate(
        ContactParameters.mujoco_default(1),
        np.concatenate([origin, q0])[None, None],
        start_velocity[None, None],
        n_steps,
    )
    poses, velocities = result.poses[0, :, :, 0], result.velocities[0, :, :, 0]
    times = dt * np.arange(1, n_steps + 1)
    turned = rotations.multiply(poses[0, :, 3:], rotations.conjugate(q0))
    np.testing.assert_allclose(rotations.to_rotation_vector(turned), times[:, None] * omega, atol=1e-9)
    np.testing.assert_allclose(velocities[0, :, 3:], np.broadcast_to(omega, (n_steps, 3)), atol=1e-9)
    com_track = poses[0, :, :3] + rotations.rotate(poses[0, :, 3:], com_body)
    # Semi-implicit Euler bends the origin's circle by O(h) (measured: CoM within 0.19 mm, origin velocity within
    # 0.3 mm/s of 0.19 m/s); reading the linear velocity as the CoM's would carry the CoM 0.1 m away.
    assert np.abs(com_track - com_world).max() < 5e-4
    expected_origin_velocity = np.cross(omega, poses[0, :, :3] - com_track)
    assert np.abs(velocities[0, :, :3] - expected_origin_velocity).max() < 1e-3


@pytest.mark.parametrize("inertia_diagonal", [(1e-3, 2e-3, 2.5e-3), None])
def test_qpos_is_the_recordings_pose_for_an_offset_mesh(inertia_diagonal):
    tetrahedron = Mesh(
        np.array([[0.02, 0.01, 0.0], [0.12, 0.0, 0.01], [0.03, 0.09, 0.0], [0.05, 0.03, 0.07]]),
        np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
    )
    data = scene([tetrahedron], masses=[0.5], inertia_diagonals=[inertia_diagonal])
    model = build_model(data, ContactParameters.mujoco_default(1))
    mujoco_data = mujoco.MjData(model)
    pose = np.concatenate([[0.3, -0.2, 0.4], rotations.from_axis_angle(np.array([1.0, -2.0, 0.5]), 2.0)])
    mujoco_data.qpos[:] = pose
    mujoco.mj_kinematics(model, mujoco_data)
    np.testing.assert_allclose(mujoco_data.xpos[1], pose[:3], atol=1e-12)
    assert rotations.angle_between(mujoco_data.xquat[1], pose[3:]) < 1e-9
    com, inertia = data.inertial(0)
    assert np.linalg.norm(com) > 0.05
    np.testing.assert_allclose(mujoco_data.xipos[1], pose[:3] + rotations.rotate(pose[3:], com), atol=1e-12)
    principal_axes = rotations.to_matrix(model.body_iquat[1])
    # MuJoCo diagonalises the explicit full inertia iteratively, to about 1e-9 of its scale.
    reassembled = principal_axes @ np.diag(model.body_inertia[1]) @ principal_axes.T
    np.testing.assert_allclose(reassembled, inertia, rtol=0, atol=1e-7 * np.abs(inertia).max())
    assert model.body_mass[1] == 0.5
    # MuJoCo recentres the mesh on its own centroid; geom pos/quat must put every vertex back where the pose says.
    mesh_vertices = model.mesh_vert[model.mesh_vertadr[0] : model.mesh_vertadr[0] + model.mesh_vertnum[0]]
    placed = mujoco_data.geom_xpos[1] + mesh_vertices @ mujoco_data.geom_xmat[1].reshape(3, 3).T
    expected = world_vertices(pose, tetrahedron.vertices)
    distances = np.linalg.norm(placed[:, None] - expected[None], axis=-1)
    assert distances.shape == (4, 4) and distances.min(axis=0).max() < 1e-6


def test_batched_parameter_sets_equal_separate_calls(cube_data):
    split = cube_data.split("test").select(range(6))
    params = [
        ContactParameters.mujoco_default(1),
        ContactParameters((0.2,), 0.3, 800.0, 60.0),
        ContactParameters((0.6,), 0.1, 3000.0, 20.0, torsional_friction=0.01, rolling_friction=0.001),
    ]
    poses0, velocities0 = split.poses[:, 0], split.velocities[:, 0]
    batched = MujocoRollouts(cube_data, nthread=2).simulate(params, poses0, velocities0, 60)
    single = MujocoRollouts(cube_data, nthread=1)
    assert batched.poses.shape == (3, 6, 60, 1, 7) and batched.velocities.shape == (3, 6, 60, 1, 6)
    for b, p in enumerate(params):
        alone = single.simulate(p, poses0, velocities0, 60)
        np.testing.assert_array_equal(batched.poses[b], alone.poses[0])
        np.testing.assert_array_equal(batched.velocities[b], alone.velocities[0])
    assert not np.array_equal(batched.poses[0], batched.poses[1])
    assert single.model(params[1]) is single.model(ContactParameters([0.2], 0.3, 800, 60))  # cached


def test_multibody_scene_has_free_joints_and_bodies_collide():
    data = scene([CUBE, CUBE, box([-0.03] * 3, [0.03] * 3)], masses=[0.37, 0.37, 0.2])
    model = build_model(data, ContactParameters((0.3, 0.5, 0.7), 0.4, 1e3, 30.0))
    assert model.njnt == 3 and all(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    assert (model.nq, model.nv, model.npair) == (21, 18, 3)
    np.testing.assert_allclose(model.pair_friction[:, 0], [0.4, 0.5, 0.7])
    # Body 0 slides into resting body 1; body 2 rests far away.
    poses0 = np.stack([rest_pose(-0.3), rest_pose(0.0), rest_pose(1.0, 1.0, 0.03)])[None]
    velocities0 = np.zeros((1, 3, 6))
    velocities0[0, 0, 0] = 2.0
    slippery = ContactParameters((0.2, 0.2, 0.2), 0.2, None, None)
    result = MujocoRollouts(data, nthread=1).simulate(slippery, poses0, velocities0, 100)
    assert result.poses.shape == (1, 1, 100, 3, 7)
    final = result.poses[0, 0, -1]
    assert final[1, 0] > 0.05  # pushed
    assert final[0, 0] < final[1, 0] - 0.099  # never interpenetrating along x by more than 1 mm
    assert np.abs(final[2, :3] - poses0[0, 2, :3]).max() < 1e-3


def test_sliding_distance_follows_floor_friction():
    data = scene([CUBE], dt=1 / 148)
    simulator = MujocoRollouts(data, nthread=1)
    frictions = [0.1, 0.2, 0.4]
    # Object friction 0: MuJoCo's max rule leaves the floor's coefficient in charge.
    params = [ContactParameters((0.0,), mu, None, None) for mu in frictions]
    speed = 1.0
    velocity = np.array([[[speed, 0.0, 0.0, 0.0, 0.0, 0.0]]])
    result = simulator.simulate(params, rest_pose()[None, None], velocity, 148)
    distances = result.poses[:, 0, -1, 0, 0]
    np.testing.assert_allclose(distances, speed**2 / (2 * np.array(frictions) * 9.81), rtol=0.05)
    swapped = simulator.simulate(ContactParameters((0.4,), 0.0, None, None), rest_pose()[None, None], velocity, 148)
    np.testing.assert_array_equal(swapped.poses[0], result.poses[2])


def test_floor_stiffness_and_damping_reach_floor_contacts():
    data = scene([CUBE])
    model = build_model(data, ContactParameters((0.3,), 0.6, 500.0, 30.0))
    np.testing.assert_array_equal(model.pair_solref, [[-500.0, -30.0]])
    mujoco_data = mujoco.MjData(model)
    mujoco_data.qpos[:] = rest_pose(half=0.049)
    mujoco.mj_forward(model, mujoco_data)
    contacts = mujoco_data.contact[: mujoco_data.ncon]
    assert mujoco_data.ncon >= 3
    np.testing.assert_array_equal(contacts.solref, np.tile([-500.0, -30.0], (mujoco_data.ncon, 1)))
    np.testing.assert_array_equal(contacts.friction[:, :2], np.full((mujoco_data.ncon, 2), 0.6))
    assert all(contacts.dim == 3)
    default = build_model(data, ContactParameters.mujoco_default(1))
    np.testing.assert_array_equal(default.pair_solref, [[0.02, 1.0]])
    # A stiffer floor holds a resting cube higher (measured sinking: 0.56, 0.084, 0.0084 mm).
    simulator = MujocoRollouts(data, nthread=1)
    params = [ContactParameters((0.5,), 0.5, k, 10.0) for k in (1e2, 1e3, 1e4)]
    result = simulator.simulate(params, rest_pose()[None, None], np.zeros((1, 1, 6)), 100)
    sinking = 0.05 - result.poses[:, 0, -1, 0, 2]
    assert np.all(sinking > 0) and np.all(sinking[1:] < 0.3 * sinking[:-1])


def test_unstable_parameters_are_flagged_without_exceptions(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # MuJoCo logs its divergence warning to MUJOCO_LOG.TXT in the working directory
    data = scene([CUBE], dt=0.5)
    simulator = MujocoRollouts(data, nthread=2)
    start = np.stack([rest_pose(), rest_pose(half=0.3)])[:, None]
    velocities = np.zeros((2, 1, 6))
    velocities[1, 0, 2] = -1.0
    stiff_undamped = ContactParameters((0.5,), 0.5, 1e4, 0.0)
    result = simulator.simulate([stiff_undamped, ContactParameters.mujoco_default(1)], start, velocities, 20)
    assert result.unstable[0].all() and np.isfinite(result.poses).all()
    # A velocity MuJoCo rejects as "huge" makes it reset the data; those frames come back as NaN.
    velocities[0, 0, 3] = 1e12
    reset = MujocoRollouts(scene([CUBE]), nthread=2).simulate(ContactParameters.mujoco_default(1), start, velocities, 5)
    assert reset.unstable[0].tolist() == [True, False]
    assert np.isnan(reset.poses[0, 0]).all() and np.isfinite(reset.poses[0, 1]).all()


def test_rollout_context_on_real_cube(cube_data):
    split = cube_data.split("test").select(range(12))
    context = make_context(split, cube_data.dt, 4)
    predicted = rollout_context(cube_data, context, ContactParameters.mujoco_default(1))
    assert predicted.shape == (12, context.horizon, 1, 7)
    np.testing.assert_array_equal(predicted[:, :4], context.poses)
    # One step from a recorded state lands within a fraction of a millimetre of the next recorded frame.
    first_error = np.linalg.norm(predicted[:, 4, 0, :3] - split.poses[:, 4, 0, :3], axis=-1)
    assert first_error.max() < 1e-3
    direct = MujocoRollouts(cube_data).simulate(
        ContactParameters.mujoco_default(1), context.poses[:, -1], context.velocities[:, -1], context.horizon - 4
    )
    np.testing.assert_array_equal(predicted[:, 4:], direct.poses[0])
    assert np.isfinite(predicted).all()
