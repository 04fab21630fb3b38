"""PyBullet as an engine: it reproduces the data it generated, follows physics in free flight, and is identified by
the same SysID search as MuJoCo."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pybullet
import pytest
from conftest import cube_mesh, falling_cubes

from contactbench import rotations
from contactbench.errors import ContactbenchError, NotApplicable
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.kinematics import hinge_anchor, hinge_child, hinge_coordinates
from contactbench.meshes import Mesh
from contactbench.models.sysid.search_space import search_space
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.scene import FORMAT, SCENE_VERSION, Scene
from contactbench.sim.articulation import Articulation
from contactbench.sim.bullet_engine import BulletEngine
from contactbench.sim.bullet_scene import BulletParameters
from contactbench.sim.bullet_tosses import BulletWorld
from contactbench.sim.engines import engine

RIGID = BulletParameters(object_friction=(0.5,), restitution=(0.0,))
COMPLIANT = replace(RIGID, contact_stiffness=1e5, contact_damping=300.0)


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """A few frictioncubes (friction 0.5, restitution 0) tosses from the project's generator."""
    spec = SceneSpec(name="frictioncubes", friction=0.5, restitution=0.0)
    path = generate_dataset(
        spec,
        tmp_path_factory.mktemp("data") / "frictioncubes",
        split_sizes={"train": 2, "val": 2, "test": 6},
        workers=1,
        progress=False,
    )
    return read_recordings(path, ["test"])


def brick_scene(dt: float) -> Scene:
    """A brick whose mesh frame is neither at its centre of mass nor along its principal axes."""
    cube = cube_mesh(0.1)
    turn = rotations.to_matrix(rotations.normalize(np.array([0.8, 0.3, -0.4, 0.2])))
    vertices = (cube.vertices * np.array([1.0, 0.6, 0.3]) + np.array([0.01, -0.02, 0.005])) @ turn.T
    meta = falling_cubes(1, 4).meta | {"dt": dt}
    return Scene(meta=meta, meshes={"meshes/cube.obj": Mesh(vertices, cube.faces)})


def test_the_generating_parameters_reproduce_generated_tosses(generated):
    """The self-identification check's premise: restarted from the context's last frame with the parameters that
    generated them, the engine reproduces the recorded tosses (a wrong world setting would show here)."""
    split = generated.split("test")
    context = make_context(split, generated.dt, 6)
    rollouts = BulletEngine().rollouts(generated.scene, nthread=1)
    predicted = rollouts.rollout_context(context, RIGID)
    error = np.linalg.norm(predicted.poses[0, :, 6:, :, :3] - split.poses[:, 6:, :, :3], axis=-1)
    assert error.max() / generated.widths()[0] < 1e-9
    assert not predicted.unstable.any()
    other = rollouts.rollout_context(context, replace(RIGID, object_friction=(0.3,))).poses[0]
    assert np.abs(other[:, 6:, 0, :3] - split.poses[:, 6:, 0, :3]).max() > 1e-3  # the parameters matter


def free_flight(dt: float, seconds: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre-of-mass error against the semi-implicit ballistic path, and angular momentum [T, 3] and its start."""
    scene = brick_scene(dt)
    com, inertia = scene.inertial(0)
    q0 = rotations.normalize(np.array([0.9, 0.1, 0.3, -0.2]))
    poses0, velocities0 = np.array([[0.0, 0.0, 2.0, *q0]]), np.array([[0.5, -0.3, 1.0, 3.0, -5.0, 7.0]])
    steps = int(round(seconds / dt))
    poses, velocities = BulletWorld(scene).toss(RIGID, poses0, velocities0, steps)
    turn = rotations.to_matrix(poses[:, 0, 3:])
    centre = poses[:, 0, :3] + turn @ com
    turn0 = rotations.to_matrix(q0)
    centre0 = poses0[0, :3] + turn0 @ com
    speed0 = velocities0[0, :3] + np.cross(velocities0[0, 3:], turn0 @ com)
    n = np.arange(1, steps + 1)[:, None]
    ballistic = centre0 + speed0 * dt * n + scene.gravity * dt**2 * n * (n + 1) / 2
    momentum = np.einsum("tij,jk,tlk,tl->ti", turn, inertia, turn, velocities[:, 0, 3:])
    return np.abs(centre - ballistic).max(), momentum, turn0 @ inertia @ turn0.T @ velocities0[0, 3:]


def test_free_flight_follows_gravity_and_keeps_angular_momentum():
    """The centre of mass follows g exactly; angular momentum is kept up to Bullet's explicit gyroscopic term, whose
    drift is first order in the step (a wrong inertial frame would not converge)."""
    drifts = []
    for dt in (0.005, 0.0025):
        centre_error, momentum, momentum0 = free_flight(dt)
        assert centre_error < 1e-12
        drifts.append(np.abs(momentum - momentum0).max() / np.linalg.norm(momentum0))
    assert drifts[0] < 0.02
    assert 1.8 < drifts[0] / drifts[1] < 2.2


def test_parameters_are_checked_and_a_compliant_contact_can_be_undone(generated):
    with pytest.raises(ContactbenchError, match="restitution"):
        BulletParameters(object_friction=(0.5,), restitution=(1.5,))
    with pytest.raises(ContactbenchError, match="together"):
        BulletParameters(object_friction=(0.5,), restitution=(0.0,), contact_stiffness=1e4)
    split = generated.split("test")
    start = split.poses[0, 5], split.velocities[0, 5]
    world = BulletWorld(generated.scene)
    rigid = world.toss(RIGID, *start, 40)[0]
    compliant = world.toss(COMPLIANT, *start, 40)[0]
    assert np.abs(compliant - rigid).max() > 1e-6
    np.testing.assert_array_equal(world.toss(RIGID, *start, 40)[0], rigid)


def test_two_workers_give_the_numbers_one_gives(generated):
    split = generated.split("test")
    context = make_context(split, generated.dt, 6)
    candidates = [RIGID, COMPLIANT]
    one = BulletEngine().rollouts(generated.scene, nthread=1)
    two = BulletEngine().rollouts(generated.scene, nthread=2)
    try:
        np.testing.assert_array_equal(
            one.rollout_context(context, candidates).poses, two.rollout_context(context, candidates).poses
        )
    finally:
        two.close()


def test_the_search_space_covers_rigid_and_compliant_contact():
    space = search_space("bullet", 2)
    for parameters in (
        BulletParameters((0.2, 0.7), (0.0, 0.5), 0.01, 0.001),
        BulletParameters((0.2, 0.7), (0.0, 0.5), contact_stiffness=2e4, contact_damping=50.0),
    ):
        back = space.from_vector(space.to_vector(parameters))
        assert space.describe(back) == pytest.approx(space.describe(parameters))
        assert (back.contact_stiffness is None) == (parameters.contact_stiffness is None)
    candidate = space.parametrization(seed=0).value
    assert candidate["contact"] in ("rigid", "compliant")
    assert space.to_parameters(candidate).object_friction == (0.5, 0.5)


def test_the_written_urdf_is_the_scene_pybullet_loads(tmp_path):
    scene = brick_scene(0.005)
    parameters = BulletParameters((0.4,), (0.3,), 0.01, 0.002, contact_stiffness=5e4, contact_damping=100.0)
    for relative, text in engine("bullet").scene_files(scene, parameters).items():
        (tmp_path / relative).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / relative).write_text(text)
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(
            str(tmp_path / "body_0.urdf"), flags=pybullet.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client
        )
        info = pybullet.getDynamicsInfo(body, -1, physicsClientId=client)
        world = BulletWorld(scene)
        mass, friction, moments, com, axes, restitution, rolling, spinning, damping, stiffness = info[:10]
        assert (mass, friction, restitution, rolling, spinning) == pytest.approx((0.37, 0.4, 0.3, 0.002, 0.01))
        assert (stiffness, damping) == pytest.approx((5e4, 100.0))
        np.testing.assert_allclose(moments, world.moments[0], rtol=1e-9)  # the principal moments
        np.testing.assert_allclose(com, world.coms[0], atol=1e-12)  # the centre of mass in the mesh frame
        assert abs(np.dot(rotations.xyzw_to_wxyz(np.array(axes)), world.axes[0])) == pytest.approx(1.0)
        world.close()
    finally:
        pybullet.disconnect(physicsClientId=client)


# ---------------------------------------------------------------- hinges


def box(size) -> Mesh:
    cube = cube_mesh(1.0)
    return Mesh(cube.vertices * np.asarray(size), cube.faces)


def hinged_pair(
    parent: Mesh,
    child: Mesh,
    parent_anchor,
    child_anchor,
    masses=(0.37, 0.37),
    gravity=(0.0, 0.0, -9.81),
    dt: float = 0.005,
    **joint,
) -> Scene:
    """Two bodies on one hinge about their mesh frames' y axis (recordings version 2)."""
    meta = {
        "format": FORMAT,
        "version": SCENE_VERSION,
        "name": "hinged-pair",
        "dt": dt,
        "gravity": list(gravity),
        "floor_z": 0.0,
        "bodies": [
            {"name": "parent", "mesh": "meshes/parent.obj", "mass": masses[0]},
            {"name": "child", "mesh": "meshes/child.obj", "mass": masses[1]},
        ],
        "joints": [
            {
                "name": "hinge",
                "type": "hinge",
                "parent": "parent",
                "child": "child",
                "parent_anchor": list(parent_anchor),
                "child_anchor": list(child_anchor),
                "axis": [0.0, 1.0, 0.0],
                **joint,
            }
        ],
        "splits": {},
    }
    return Scene(meta=meta, meshes={"meshes/parent.obj": parent, "meshes/child.obj": child})


def bricks(**options) -> Scene:
    """Two bricks whose mesh frames are neither at their centres of mass nor along their principal axes, on a hinge
    beyond their ends."""
    brick = brick_scene(0.005).body_mesh(0)
    return hinged_pair(brick, brick, (0.09, 0.01, 0.0), (-0.08, 0.0, 0.02), masses=(0.37, 0.2), **options)


def hinged_state(scene: Scene, angle: float, rate: float, height: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    parent = np.array([0.1, -0.2, height, *rotations.normalize(np.array([0.9, 0.1, 0.3, -0.2]))])
    parent_velocity = np.array([0.5, -0.3, 1.0, 3.0, -5.0, 7.0])
    child, child_velocity = hinge_child(parent, parent_velocity, scene.joints[0], angle, rate)
    return np.stack([parent, child]), np.stack([parent_velocity, child_velocity])


def centre_of_mass(scene: Scene, poses: np.ndarray) -> np.ndarray:
    coms = np.array([scene.inertial(k)[0] for k in range(scene.n_bodies)])
    masses = np.array([body.mass for body in scene.bodies])
    centres = poses[..., :3] + rotations.rotate(poses[..., 3:], np.broadcast_to(coms, poses.shape[:-1] + (3,)))
    return np.einsum("k,...kd->...d", masses / masses.sum(), centres)


def energy(scene: Scene, poses: np.ndarray, velocities: np.ndarray) -> np.ndarray:
    """Kinetic plus potential energy [...] of poses [..., K, 7] and world velocities [..., K, 6]."""
    total = 0.0
    for k, body in enumerate(scene.bodies):
        com, inertia = scene.inertial(k)
        turn = rotations.to_matrix(poses[..., k, 3:])
        offset = np.einsum("...ij,j->...i", turn, com)
        linear = velocities[..., k, :3] + np.cross(velocities[..., k, 3:], offset)
        spin = np.einsum("...ji,...j->...i", turn, velocities[..., k, 3:])  # in the mesh frame
        total = (
            total
            + 0.5 * body.mass * np.sum(linear**2, axis=-1)
            + 0.5 * np.einsum("...i,ij,...j->...", spin, inertia, spin)
        )
        total = total - body.mass * np.einsum("...d,d->...", poses[..., k, :3] + offset, scene.gravity)
    return total


RIGID_PAIR = BulletParameters(object_friction=(0.5, 0.5), restitution=(0.0, 0.0))


def swing(scene: Scene, dt: float, seconds: float, spin=(3.0, -5.0, 7.0), parameters=RIGID_PAIR):
    """A toss of the pair high in the air, the hinge at 0.4 rad turning at -3 rad/s: initial and output states."""
    scene = replace(scene, meta=scene.meta | {"dt": dt})
    parent = np.array([0.1, -0.2, 2.0, *rotations.normalize(np.array([0.9, 0.1, 0.3, -0.2]))])
    parent_velocity = np.array([0.5, -0.3, 1.0, *spin])
    child, child_velocity = hinge_child(parent, parent_velocity, scene.joints[0], 0.4, -3.0)
    poses0, velocities0 = np.stack([parent, child]), np.stack([parent_velocity, child_velocity])
    world = BulletWorld(scene)
    try:
        return (poses0, velocities0, *world.toss(parameters, poses0, velocities0, int(round(seconds / dt))))
    finally:
        world.close()


def test_a_tumbling_hinged_pair_falls_with_g_keeps_its_hinge_and_is_where_pybullet_puts_its_link():
    """Every output frame keeps the hinge (anchors together) and the child is PyBullet's own link (its frame, centre
    of mass and velocities, to PyBullet's single-precision link state). The pair's centre of mass falls with g up to
    PyBullet's integration of the jointed pair in its joint coordinates, first order in the step: exact where nothing
    turns, converging where it tumbles (a wrong mass, inertia or frame would not converge)."""
    scene = bricks()
    engine("bullet").check_scene(scene)
    joint = scene.joints[0]
    world = BulletWorld(scene)
    poses0, velocities0 = swing(scene, 0.005, 0.01)[:2]
    poses, velocities = world.toss(RIGID_PAIR, poses0, velocities0, 100)
    gap = hinge_anchor(poses[:, 0], joint) - hinge_anchor(poses[:, 1], replace(joint, parent_anchor=joint.child_anchor))
    assert np.abs(gap).max() < 1e-12
    angle = hinge_coordinates(poses[:, 0], velocities[:, 0], poses[:, 1], velocities[:, 1], joint)[0]
    assert np.ptp(angle) > 0.3  # it swung
    link = pybullet.getLinkState(
        world.bodies[0], 0, computeLinkVelocity=1, computeForwardKinematics=1, physicsClientId=world.client
    )
    world.close()
    com = scene.inertial(1)[0]
    turn = rotations.to_matrix(poses[-1, 1, 3:])
    np.testing.assert_allclose(link[4], hinge_anchor(poses[-1, 0], joint), atol=1e-6)  # the link frame: the anchor
    np.testing.assert_allclose(link[0], poses[-1, 1, :3] + turn @ com, atol=1e-6)
    assert abs(np.dot(rotations.xyzw_to_wxyz(np.array(link[5])), poses[-1, 1, 3:])) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(link[6], velocities[-1, 1, :3] + np.cross(velocities[-1, 1, 3:], turn @ com), atol=1e-6)
    np.testing.assert_allclose(link[7], velocities[-1, 1, 3:], atol=1e-6)

    def falling_error(dt: float, spin, rate: float = -3.0) -> float:
        poses0, velocities0, poses, _ = swing(scene, dt, 0.25, spin)
        centre = centre_of_mass(scene, np.concatenate([poses0[None], poses]))
        falling = np.diff(centre, n=2, axis=0) / dt**2
        return np.abs(falling - scene.gravity).max() / np.linalg.norm(scene.gravity)

    errors = [falling_error(dt, (3.0, -5.0, 7.0)) for dt in (0.005, 0.0025)]
    assert errors[0] < 0.03 and 1.8 < errors[0] / errors[1] < 2.2
    still = replace(scene, meta=scene.meta | {"dt": 0.005})
    poses0, velocities0 = np.stack([[0.0, 0.0, 2.0, 1.0, 0, 0, 0]] * 2), np.tile([0.5, -0.3, 1.0, 0, 0, 0], (2, 1))
    poses0[1] = hinge_child(poses0[0], velocities0[0], joint, 0.3, 0.0)[0]
    poses = np.concatenate([poses0[None], BulletWorld(still).toss(RIGID_PAIR, poses0, velocities0, 50)[0]])
    falling = np.diff(centre_of_mass(still, poses), n=2, axis=0) / still.dt**2
    assert np.abs(falling - still.gravity).max() < 1e-6 * np.linalg.norm(still.gravity)


def test_a_free_hinged_pair_gains_no_energy_swinging_and_converges_tumbling():
    """Without gravity: swinging about the hinge the pair's energy never grows; tumbling, PyBullet's explicit
    velocity terms of the jointed pair add energy at first order in the step (it halves with the step)."""
    scene = bricks(gravity=(0.0, 0.0, 0.0))
    poses0, velocities0, poses, velocities = swing(scene, 0.005, 1.0, spin=(0.0, 0.0, 0.0))
    start = energy(scene, poses0, velocities0)
    assert energy(scene, poses, velocities).max() <= start * (1 + 2e-5)
    assert energy(scene, poses, velocities)[-1] <= start
    gains = []
    for dt in (0.005, 0.0025):
        poses0, velocities0, poses, velocities = swing(scene, dt, 0.5)
        gains.append(energy(scene, poses, velocities).max() - energy(scene, poses0, velocities0))
    assert 1.8 < gains[0] / gains[1] < 2.2


def coaxial(**joint) -> Scene:
    """Two bars side by side on one axle through both centres of mass, without gravity."""
    bar = box((0.1, 0.04, 0.04))
    return hinged_pair(bar, bar, (0.0, 0.03, 0.0), (0.0, -0.03, 0.0), masses=(0.37, 0.2), gravity=(0, 0, 0), **joint)


def test_joint_damping_slows_the_relative_spin_as_predicted_per_parameter_set():
    """Spinning about the axle, the torque -c r before each step takes r to r (1 - c h (1/I1 + 1/I2)) and keeps the
    pair's angular momentum; the world applies each candidate's damping and inertia scale without a rebuild."""
    scene = coaxial(damping=0.002)
    poses0 = np.array([[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0], [0.0, 0.06, 1.0, 1.0, 0.0, 0.0, 0.0]])
    velocities0 = np.array([[0.0, 0.0, 0.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 0.0, -3.0, 0.0]])
    world = BulletWorld(scene)
    inertia = np.array([scene.inertial(k)[1][1, 1] for k in range(2)])
    steps = np.arange(1, 101)
    for damping, scale in ((None, 1.0), (0.004, 1.0), (0.004, 2.0), (0.0, 1.0)):
        articulation = None if damping is None else Articulation((damping,), (0.0,), scale)
        c = 0.002 if damping is None else damping
        poses, velocities = world.toss(replace(RIGID_PAIR, articulation=articulation), poses0, velocities0, 100)
        rate = velocities[:, 1, 4] - velocities[:, 0, 4]
        expected = -5.0 * (1 - c * scene.dt * np.sum(1 / (scale * inertia))) ** steps
        np.testing.assert_allclose(rate, expected, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(velocities[:, :, 4] @ inertia, 2.0 * inertia[0] - 3.0 * inertia[1], rtol=1e-9)
    world.close()


def test_joint_friction_holds_a_link_against_a_small_torque():
    """A light bar held out sideways from a heavy block on the floor: its weight's torque about the hinge is smaller
    than the joint's Coulomb friction, so it stays; without friction, or with less, it swings down."""
    block, bar = box((0.2, 0.2, 0.1)), box((0.1, 0.02, 0.02))
    scene = hinged_pair(block, bar, (0.11, 0.0, 0.0), (-0.06, 0.0, 0.0), masses=(20.0, 0.1))
    torque = 0.1 * 9.81 * 0.06  # N m, the bar's weight about the hinge
    poses0 = np.array([[0.0, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0], [0.17, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0]])
    velocities0 = np.zeros((2, 6))
    world = BulletWorld(scene)
    angles = {}
    for friction in (2 * torque, 0.5 * torque, 0.0):
        parameters = replace(RIGID_PAIR, articulation=Articulation((0.0,), (friction,)))
        poses, velocities = world.toss(parameters, poses0, velocities0, 100)
        angles[friction] = hinge_coordinates(
            poses[:, 0], velocities[:, 0], poses[:, 1], velocities[:, 1], scene.joints[0]
        )[0]
    world.close()
    assert np.abs(angles[2 * torque]).max() < 1e-3
    assert angles[0.5 * torque][-1] > 0.1 and angles[0.0][-1] > angles[0.5 * torque][-1]


def test_the_search_space_round_trips_an_articulation():
    space = search_space("bullet", 2, 1)
    assert space.names[-3:] == ["joint_damping_0", "joint_friction_0", "inertia_scale"]
    for parameters in (
        BulletParameters((0.2, 0.7), (0.0, 0.5), 0.01, 0.001, articulation=Articulation((0.01,), (0.02,), 1.5)),
        BulletParameters(
            (0.2, 0.7),
            (0.0, 0.5),
            contact_stiffness=2e4,
            contact_damping=50.0,
            articulation=Articulation((0.0,), (0.05,), 0.5),
        ),
    ):
        back = space.from_vector(space.to_vector(parameters))
        assert back.articulation == pytest.approx(parameters.articulation)
        assert space.describe(back) == pytest.approx(space.describe(parameters))
    candidate = space.to_parameters(space.parametrization(seed=0).value)
    assert candidate.articulation == Articulation((0.0,), (0.0,), 1.0)
    assert hash(candidate) == hash(replace(candidate))  # parameters key caches


def test_joints_pybullet_cannot_build_are_refused_in_one_line():
    bullet = engine("bullet")
    bullet.check_scene(bricks(range=[-1.0, 1.0], damping=0.01, friction=0.02))
    for field, message in (("type", "field 'type' is 'slider'"), ("stiffness", "field 'stiffness' is not one")):
        scene = bricks()
        scene.meta["joints"][0][field] = "slider" if field == "type" else 1.0
        with pytest.raises(NotApplicable, match=f"hinged-pair: joints\\[0\\] {message}") as error:
            bullet.check_scene(scene)
        assert "\n" not in str(error.value)


def test_a_joint_range_stops_the_hinge():
    scene = coaxial(range=[-0.3, 0.3])
    poses0 = np.array([[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0], [0.0, 0.06, 1.0, 1.0, 0.0, 0.0, 0.0]])
    velocities0 = np.array([[0.0, 0.0, 0.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 0.0, -3.0, 0.0]])
    poses, velocities = BulletWorld(scene).toss(RIGID_PAIR, poses0, velocities0, 100)
    angle = hinge_coordinates(poses[:, 0], velocities[:, 0], poses[:, 1], velocities[:, 1], scene.joints[0])[0]
    assert angle.min() > -0.35 and angle.min() < -0.25  # free, it would turn -2.5 rad


def test_the_written_urdf_of_a_hinged_pair_is_the_world_pybullet_builds(tmp_path):
    scene = bricks(range=[-2.0, 2.5])
    articulation = Articulation((0.004,), (0.03,), 1.5)
    parameters = replace(RIGID_PAIR, object_friction=(0.4, 0.6), articulation=articulation)
    files = engine("bullet").scene_files(scene, parameters)
    assert "body_1.urdf" not in files  # the child is a link of its parent's robot
    for relative, text in files.items():
        (tmp_path / relative).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / relative).write_text(text)
    world = BulletWorld(scene)
    world.toss(parameters, *swing(scene, 0.005, 0.01)[:2], 1)
    client = pybullet.connect(pybullet.DIRECT)
    try:
        flags = pybullet.URDF_USE_INERTIA_FROM_FILE | pybullet.URDF_USE_SELF_COLLISION
        body = pybullet.loadURDF(str(tmp_path / "body_0.urdf"), flags=flags, physicsClientId=client)
        assert pybullet.getNumJoints(body, physicsClientId=client) == 1
        joint = pybullet.getJointInfo(body, 0, physicsClientId=client)
        built = pybullet.getJointInfo(world.bodies[0], 0, physicsClientId=world.client)
        assert joint[2] == pybullet.JOINT_REVOLUTE and joint[6:10] == pytest.approx((0.004, 0.03, -2.0, 2.5))
        np.testing.assert_allclose(joint[13:15], built[13:15], atol=1e-7)  # axis, joint frame in the parent
        for link in (-1, 0):
            loaded = pybullet.getDynamicsInfo(body, link, physicsClientId=client)
            expected = pybullet.getDynamicsInfo(world.bodies[0], link, physicsClientId=world.client)
            assert loaded[:2] == pytest.approx(expected[:2])  # mass, friction
            np.testing.assert_allclose(loaded[2], expected[2], rtol=1e-9)  # the principal moments, scaled
            np.testing.assert_allclose(loaded[3], expected[3], atol=1e-7)  # the inertial frame in the link's
    finally:
        pybullet.disconnect(physicsClientId=client)
        world.close()
