"""The diagnosis' effects in PyBullet and Drake (their parameters' `effects`) mean what they mean in MuJoCo: free
flight agrees with MuJoCo's to a small fraction of the effect, a raised floor holds a body higher, a tilted floor
(and PyBullet's anisotropic one) sends a slide the way MuJoCo's does."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from contactbench import rotations
from contactbench.recordings import read_recordings
from contactbench.sim.bullet_scene import BulletParameters
from contactbench.sim.effects import SceneEffects
from contactbench.sim.engines import engine
from contactbench.sim.mujoco_scene import ContactParameters

FLIGHT_POSE = np.array([[[0.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0]]])
FLIGHT_VELOCITY = np.array([[[1.0, 0.5, 2.0, 3.0, -2.0, 5.0]]])


@pytest.fixture(scope="module")
def cube():
    return read_recordings("assets/contactnets_cube", ["val"])


@pytest.fixture(scope="module")
def elbow():
    return read_recordings("assets/contactnets_elbow", ["val"])


def _parameters(name: str, friction: float, effects: SceneEffects, n_bodies: int = 1):
    if name == "bullet":
        return BulletParameters((friction,) * n_bodies, (0.0,) * n_bodies, effects=effects)
    return replace(
        engine("drake").default_parameters(n_bodies),
        object_friction=(friction,) * n_bodies,
        floor_friction=friction,
        effects=effects,
    )


def _both(scene, effects: SceneEffects, poses, velocities, frames: int, friction: float = 0.5, name: str = "bullet"):
    """The same toss in MuJoCo and in the named engine: poses [T, K, 7] each."""
    mujoco = engine("mujoco").rollouts(scene)
    other = engine(name).rollouts(scene, nthread=1)
    n_bodies = scene.n_bodies
    try:
        in_mujoco = mujoco.simulate(
            [ContactParameters((friction,) * n_bodies, friction, None, None, effects=effects)],
            poses,
            velocities,
            frames,
        ).poses[0, 0]
        in_other = other.simulate([_parameters(name, friction, effects, n_bodies)], poses, velocities, frames).poses[
            0, 0
        ]
    finally:
        other.close()
    return in_mujoco, in_other


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(
        np.abs(rotations.to_rotation_vector(rotations.multiply(a[..., 3:], rotations.conjugate(b[..., 3:])))).max()
    )


@pytest.mark.parametrize("name", ["bullet", "drake"])
@pytest.mark.parametrize(
    "effects",
    [
        SceneEffects(gravity_scale=0.9),
        SceneEffects(fluid_density=50.0, wind=(2.0, -1.0, 0.0)),
        SceneEffects(com_offset=(0.01, 0.005, -0.01)),
        SceneEffects(inertia_scale=(1.5, 0.8, 1.0)),
    ],
    ids=["gravity", "drag_in_wind", "com_offset", "inertia"],
)
def test_free_flight_with_an_effect_follows_mujocos(cube, effects, name):
    in_mujoco, in_bullet = _both(cube, effects, FLIGHT_POSE, FLIGHT_VELOCITY, 40, name=name)
    plain, _ = _both(cube, SceneEffects(), FLIGHT_POSE, FLIGHT_VELOCITY, 40)
    size = max(np.abs(in_mujoco[..., :3] - plain[..., :3]).max(), _angle(in_mujoco, plain))
    assert size > 1e-3  # the effect changes the flight
    assert np.abs(in_mujoco[..., :3] - in_bullet[..., :3]).max() < 0.05 * size
    assert _angle(in_mujoco, in_bullet) < 0.05 * size


@pytest.mark.parametrize("name", ["bullet", "drake"])
def test_a_hinged_pair_in_wind_flies_as_in_mujoco(elbow, name):
    """Drag acts on a hinge's child as on its parent: the real elbow, raised clear of the floor, tumbling."""
    split = elbow.split("val")
    poses, velocities = split.poses[:1, 1].copy(), split.velocities[:1, 1].copy()  # frame 0 has no velocity
    poses[..., 2] += 2.0
    effects = SceneEffects(fluid_density=50.0, wind=(2.0, -1.0, 0.0))
    in_mujoco, in_other = _both(elbow, effects, poses, velocities, 40, name=name)
    plain, _ = _both(elbow, SceneEffects(), poses, velocities, 40)
    size = max(np.abs(in_mujoco[..., :3] - plain[..., :3]).max(), _angle(in_mujoco, plain))
    assert size > 1e-3
    assert np.abs(in_mujoco[..., :3] - in_other[..., :3]).max() < 0.05 * size
    assert _angle(in_mujoco, in_other) < 0.05 * size


@pytest.mark.parametrize("name", ["bullet", "drake"])
def test_a_raised_floor_holds_a_dropped_cube_higher_and_a_tilted_one_sends_it_downhill(cube, name):
    half = cube.widths()[0] / 2
    drop = np.array([[[0.0, 0.0, half + 0.1, 1.0, 0.0, 0.0, 0.0]]])
    still = np.zeros((1, 1, 6))
    for offset in (0.0, 0.05):
        _, in_other = _both(cube, SceneEffects(floor_offset=offset), drop, still, 120, name=name)
        assert in_other[-1, 0, 2] == pytest.approx(cube.floor_z + offset + half, abs=3e-3)
    resting = np.array([[[0.0, 0.0, half + 0.005, 1.0, 0.0, 0.0, 0.0]]])
    in_mujoco, in_other = _both(cube, SceneEffects(floor_tilt=(0.0, 0.3)), resting, still, 60, 0.1, name=name)
    downhill = np.sign(in_mujoco[-1, 0, 0] - in_mujoco[0, 0, 0])
    assert downhill != 0 and np.sign(in_other[-1, 0, 0] - in_other[0, 0, 0]) == downhill
    assert abs(in_other[-1, 0, 0] - in_other[0, 0, 0]) > 0.05


def test_a_slide_goes_further_along_pybullets_slippery_axis_as_in_mujoco(cube):
    half = cube.widths()[0] / 2
    resting = np.array([[[0.0, 0.0, half + 0.005, 1.0, 0.0, 0.0, 0.0]]])
    travelled = {}
    for axis in (0, 1):
        velocity = np.zeros((1, 1, 6))
        velocity[0, 0, axis] = 1.0
        in_mujoco, in_bullet = _both(cube, SceneEffects(friction_anisotropy=4.0), resting, velocity, 60, 0.3)
        travelled[axis] = (in_mujoco[-1, 0, axis], in_bullet[-1, 0, axis])
    assert (travelled[0][0] > travelled[1][0]) == (travelled[0][1] > travelled[1][1])
    assert abs(travelled[0][1] - travelled[1][1]) > 0.2 * min(travelled[0][1], travelled[1][1])
