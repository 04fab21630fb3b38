"""PyBullet as an engine: it reproduces the data it generated, follows physics in free flight, and is identified by
the same SysID search as MuJoCo."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pybullet
import pytest
from conftest import cube_mesh, falling_cubes

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.meshes import Mesh
from contactbench.models.sysid.search_space import search_space
from contactbench.protocol import make_context
from contactbench.recordings import Scene, read_recordings
from contactbench.sim.bullet_engine import BulletEngine, BulletParameters, BulletWorld
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
