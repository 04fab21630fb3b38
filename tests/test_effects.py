"""Concealed effects: PyBullet does what each effect says, MuJoCo's model of it agrees, and the meta stays silent."""
from __future__ import annotations

import numpy as np
import pytest

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.generation.bullet import BulletScene
from contactbench.generation.effects import EFFECT_NAMES, ConcealedEffects
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import BulletSettings, SceneSpec
from contactbench.generation.solids import WIDTH, solid
from contactbench.recordings import read_recordings
from contactbench.sim.mujoco_scene import ContactParameters, SceneEffects
from contactbench.sim.rollout import MujocoRollouts

SETTINGS = BulletSettings()
CUBE = solid(6)
SPEC = SceneSpec("effects", friction=0.5, restitution=0.0)


def fly(effects: ConcealedEffects, velocity=(2.0, 0.0, 0.0, 0.0, 0.0, 0.0), frames: int = 30, orientation=(1.0, 0.0, 0.0, 0.0)):
    poses0 = np.array([[0.0, 0.0, 3.0, *orientation]])
    with BulletScene(CUBE, SPEC, SETTINGS, effects) as scene:
        return scene.simulate(poses0, np.array([velocity], dtype=float), frames)


def test_air_drag_is_quadratic_and_opposes_the_motion():
    poses, velocities = fly(ConcealedEffects.named(["air_drag"], 1.0))
    # Semi-implicit Euler: v_{t+1} - v_t = dt (g + F(v_t) / m), F = -1/2 rho w^2 |v| v.
    dv = np.diff(velocities[:, 0, :3], axis=0) / SETTINGS.dt - SETTINGS.gravity
    v = velocities[:-1, 0, :3]
    expected = -0.5 * 60.0 * WIDTH**2 * np.linalg.norm(v, axis=1, keepdims=True) * v / SETTINGS.mass
    np.testing.assert_allclose(dv, expected, atol=1e-9)
    assert np.abs(dv).max() > 0.5  # a visible deceleration, not rounding


def test_wind_pushes_a_body_at_rest_in_the_air():
    _, velocities = fly(ConcealedEffects.named(["wind"], 2.0), velocity=(0.0,) * 6, frames=10)
    assert velocities[-1, 0, 0] > 0.01 and velocities[-1, 0, 1] > 0.005  # downwind: wind = (2, 1) m/s


def test_com_offset_moves_the_centre_of_mass_not_the_recorded_frame():
    offset = np.array([0.012, -0.008, 0.0]) * 2
    poses, velocities = fly(ConcealedEffects.named(["com_offset"], 2.0), velocity=(0.5, 0.0, 0.0, 4.0, -3.0, 6.0))
    centre = poses[:, 0, :3] + rotations.rotate(poses[:, 0, 3:], offset)
    times = np.arange(len(poses)) * SETTINGS.dt
    # The true centre of mass flies a parabola under g exactly; the mesh frame's origin wobbles around it.
    for axis in range(3):
        fitted = np.polyfit(times, centre[:, axis], 2)
        np.testing.assert_allclose(2 * fitted[0], SETTINGS.gravity[axis], atol=1e-6)
    origin_acceleration = np.diff(poses[:, 0, :3], 2, axis=0) / SETTINGS.dt**2 - SETTINGS.gravity
    assert np.abs(origin_acceleration).max() > 1.0  # centripetal: omega^2 |offset| ~ 2.4 m/s^2
    # Recorded velocities are the mesh frame origin's (v_com - w x R offset): they match its positions' backward
    # differences up to the rotation within a step, |w|^2 |offset| dt / 2 ~ 7e-3 m/s here, not the centre's 0.1 m/s.
    difference = np.abs(np.diff(poses[:, 0, :3], axis=0) / SETTINGS.dt - velocities[1:, 0, :3]).max()
    assert difference < 1e-2


def test_floor_offset_and_tilt_move_the_resting_height():
    for name, strength in (("floor_offset", 1.0), ("floor_tilt", 1.0)):
        effects = ConcealedEffects.named([name], strength)
        start = np.array([[0.0, 0.0, WIDTH / 2 + 0.02, 1.0, 0.0, 0.0, 0.0]])
        with BulletScene(CUBE, SPEC, SETTINGS, effects) as scene:
            poses, _ = scene.simulate(start, np.zeros((1, 6)), 140)
        if name == "floor_offset":
            assert abs(poses[-1, 0, 2] - (WIDTH / 2 + 0.008)) < 5e-4
        else:  # the cube settles flat on the tilted floor: tilted by the floor's angle
            tilt = rotations.angle_between(poses[-1, 0, 3:], np.array([1.0, 0.0, 0.0, 0.0]))
            assert abs(tilt - np.hypot(0.025, 0.012)) < 3e-3


def test_mujoco_models_the_floor_offset_and_the_drag_like_pybullet():
    data = _dataset_stub()
    rollouts = MujocoRollouts(data, nthread=1)
    base = ContactParameters((0.5,), 0.0, None, None)
    raised = ContactParameters((0.5,), 0.0, None, None, effects=SceneEffects(floor_offset=0.008))
    start = np.array([[[0.0, 0.0, WIDTH / 2 + 0.02, 1.0, 0.0, 0.0, 0.0]]])
    result = rollouts.simulate([base, raised], start, np.zeros((1, 1, 6)), 140)
    rest = result.poses[:, 0, -1, 0, 2]
    assert abs((rest[1] - rest[0]) - 0.008) < 2e-4
    # Fluid drag: a cube thrown along x high above the floor loses speed only with a fluid.
    flying = np.array([[[0.0, 0.0, 3.0, 1.0, 0.0, 0.0, 0.0]]])
    fluid = ContactParameters((0.5,), 0.0, None, None, effects=SceneEffects(fluid_density=60.0))
    speed = rollouts.simulate([base, fluid], flying, np.array([[[2.0, 0, 0, 0, 0, 0]]]), 30).qvel[:, 0, -1, 0, 0]
    assert speed[0] == pytest.approx(2.0)
    # MuJoCo's box-equivalent drag along a body axis, -1/2 rho w^2 |v_x| v_x, integrates to v0 / (1 + c v0 t / m):
    # the law the generator applies to |v| v (PyBullet's cube also falls, so there it brakes a little more).
    c, t = 0.5 * 60.0 * WIDTH**2, 30 * SETTINGS.dt
    assert speed[1] == pytest.approx(2.0 / (1 + c * 2.0 * t / SETTINGS.mass), rel=0.01)


def _dataset_stub():
    path = generate_dataset(SPEC, _dataset_stub.root / "stub", split_sizes={"train": 1}, workers=1, progress=False)
    return read_recordings(path)


@pytest.fixture(autouse=True)
def _stub_root(tmp_path):
    _dataset_stub.root = tmp_path


def test_effects_leave_the_tosses_and_meta_alone_except_the_generator_record(tmp_path):
    sizes = {"train": 3, "val": 2, "test": 2}
    plain = read_recordings(generate_dataset(SPEC, tmp_path / "plain", split_sizes=sizes, workers=1, progress=False))
    tilted = read_recordings(generate_dataset(SPEC, tmp_path / "tilted", split_sizes=sizes, workers=1, progress=False, effects=("floor_tilt",), effect_strength=2.0))
    for split in sizes:
        np.testing.assert_array_equal(plain.split(split).poses[:, 0], tilted.split(split).poses[:, 0])  # same initial states
        assert np.abs(plain.split(split).poses - tilted.split(split).poses).max() > 1e-3  # different motion
    assert {k: v for k, v in plain.meta.items() if k != "generator"} == {k: v for k, v in tilted.meta.items() if k != "generator"}
    assert tilted.meta["generator"]["effects"] == [{"name": "floor_tilt", "parameters": {"floor_tilt_x": 0.05, "floor_tilt_y": -0.024}}]
    assert plain.meta["generator"]["effects"] == []


def test_every_library_name_has_a_pybullet_switch_and_unknown_names_are_refused():
    for name in EFFECT_NAMES:
        assert ConcealedEffects.named([name]) != ConcealedEffects(), name
    with pytest.raises(ContactbenchError, match="unknown effect 'gravity_waves'"):
        ConcealedEffects.named(["gravity_waves"])
