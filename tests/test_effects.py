"""Concealed effects: PyBullet does what each effect says, MuJoCo's model of it agrees, and the meta stays silent."""

from __future__ import annotations

import numpy as np
import pytest

from contactbench import rotations
from contactbench.errors import ContactbenchError
from contactbench.generation.bullet import BulletScene
from contactbench.generation.effects import ConcealedEffects
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.generation.solids import WIDTH, solid
from contactbench.recordings import read_recordings
from contactbench.sim.bullet_world import BulletSettings
from contactbench.sim.effects import EFFECT_NAMES
from contactbench.sim.mujoco_scene import ContactParameters, SceneEffects
from contactbench.sim.rollout import MujocoRollouts

SETTINGS = BulletSettings()
CUBE = solid(6)
SPEC = SceneSpec("effects", friction=0.5, restitution=0.0)


def fly(
    effects: ConcealedEffects,
    velocity=(2.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    frames: int = 30,
    orientation=(1.0, 0.0, 0.0, 0.0),
):
    poses0 = np.array([[0.0, 0.0, 3.0, *orientation]])
    with BulletScene(CUBE, SPEC, SETTINGS, effects) as scene:
        return scene.simulate(poses0, np.array([velocity], dtype=float), frames)


def test_air_drag_is_quadratic_opposes_the_motion_and_matches_mujocos_fluid_model():
    poses, velocities = fly(ConcealedEffects.named(["air_drag"], 1.0), velocity=(2.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    # Semi-implicit Euler: v_{t+1} - v_t = dt (g + F(v_t) / m); for an axis-aligned cube F_i = -1/2 rho w^2 |v_i| v_i.
    dv = np.diff(velocities[:, 0, :3], axis=0) / SETTINGS.dt - SETTINGS.gravity
    v = velocities[:-1, 0, :3]
    expected = -0.5 * 60.0 * WIDTH**2 * np.abs(v) * v / SETTINGS.mass
    np.testing.assert_allclose(dv, expected, atol=1e-9)
    assert np.abs(dv).max() > 0.5  # a visible deceleration, not rounding
    # A tumbling throw: PyBullet with the concealed drag and MuJoCo with its own fluid model fly the same path.
    throw = (1.5, -0.8, 0.5, 6.0, -4.0, 9.0)
    orientation = rotations.from_axis_angle(np.array([1.0, 2.0, 3.0]), 0.7)
    bullet_poses, _ = fly(ConcealedEffects.named(["air_drag"], 2.0), velocity=throw, frames=40, orientation=orientation)
    rollouts = MujocoRollouts(_dataset_stub(), nthread=1)
    fluid = ContactParameters((0.5,), 0.0, None, None, effects=SceneEffects(fluid_density=120.0))
    mujoco_poses = rollouts.simulate([fluid], bullet_poses[None, 0], np.array([[throw]]), 39).poses[0, 0, :, 0]
    np.testing.assert_allclose(mujoco_poses[:, :3], bullet_poses[1:, 0, :3], atol=2e-4)
    plain, _ = fly(ConcealedEffects(), velocity=throw, frames=40, orientation=orientation)
    assert np.abs(plain[-1, 0, :3] - bullet_poses[-1, 0, :3]).max() > 10 * 2e-4  # the drag is what they share


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


def test_mujoco_models_a_raised_floor():
    data = _dataset_stub()
    rollouts = MujocoRollouts(data, nthread=1)
    base = ContactParameters((0.5,), 0.0, None, None)
    raised = ContactParameters((0.5,), 0.0, None, None, effects=SceneEffects(floor_offset=0.008))
    start = np.array([[[0.0, 0.0, WIDTH / 2 + 0.02, 1.0, 0.0, 0.0, 0.0]]])
    result = rollouts.simulate([base, raised], start, np.zeros((1, 1, 6)), 140)
    rest = result.poses[:, 0, -1, 0, 2]
    assert abs((rest[1] - rest[0]) - 0.008) < 2e-4


def _dataset_stub():
    path = generate_dataset(SPEC, _dataset_stub.root / "stub", split_sizes={"train": 1}, workers=1, progress=False)
    return read_recordings(path)


@pytest.fixture(autouse=True)
def _stub_root(tmp_path):
    _dataset_stub.root = tmp_path


def test_effects_leave_the_tosses_and_meta_alone_except_the_generator_record(tmp_path):
    sizes = {"train": 3, "val": 2, "test": 2}
    plain = read_recordings(generate_dataset(SPEC, tmp_path / "plain", split_sizes=sizes, workers=1, progress=False))
    tilted = read_recordings(
        generate_dataset(
            SPEC,
            tmp_path / "tilted",
            split_sizes=sizes,
            workers=1,
            progress=False,
            effects=("floor_tilt",),
            effect_strength=2.0,
        )
    )
    for split in sizes:
        np.testing.assert_array_equal(
            plain.split(split).poses[:, 0], tilted.split(split).poses[:, 0]
        )  # same initial states
        assert np.abs(plain.split(split).poses - tilted.split(split).poses).max() > 1e-3  # different motion
    assert {k: v for k, v in plain.meta.items() if k != "generator"} == {
        k: v for k, v in tilted.meta.items() if k != "generator"
    }
    assert tilted.meta["generator"]["effects"] == [
        {"name": "floor_tilt", "parameters": {"floor_tilt_x": 0.05, "floor_tilt_y": -0.024}}
    ]
    assert plain.meta["generator"]["effects"] == []


def test_every_library_name_has_a_pybullet_switch_and_unknown_names_are_refused():
    for name in EFFECT_NAMES:
        assert ConcealedEffects.named([name]) != ConcealedEffects(), name
    with pytest.raises(ContactbenchError, match="unknown effect 'gravity_waves'"):
        ConcealedEffects.named(["gravity_waves"])


def test_a_batch_mixing_an_offset_centre_of_mass_with_plain_models_matches_stepping_each_alone():
    # An offset centre of mass makes MuJoCo lay its data out differently: data made for the plain scene gave NaN.
    rollouts = MujocoRollouts(_dataset_stub(), nthread=2)
    plain = ContactParameters((0.5,), 0.0, 1000.0, 50.0)
    offset = ContactParameters((0.5,), 0.0, 1000.0, 50.0, effects=SceneEffects(com_offset=(0.01, -0.005, 0.0)))
    poses0 = np.array([[[0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0]]])
    velocities0 = np.array([[[1.0, 0.0, 0.0, 2.0, 0.0, 3.0]]])
    mixed = rollouts.simulate([plain, offset], poses0, velocities0, 60)
    assert not mixed.unstable.any() and np.isfinite(mixed.poses).all()
    alone = MujocoRollouts(_dataset_stub(), nthread=1).simulate([offset], poses0, velocities0, 60)
    np.testing.assert_allclose(mixed.poses[1], alone.poses[0], atol=1e-12)
    assert np.abs(mixed.poses[0] - mixed.poses[1]).max() > 1e-3


def test_wind_and_air_drag_together_do_not_depend_on_their_order():
    both = ConcealedEffects.named(["air_drag", "wind"], 2.0)
    assert both == ConcealedEffects.named(["wind", "air_drag"], 2.0)
    assert both.fluid_density == 120.0 and both.wind == (2.0, 1.0, 0.0)
    assert ConcealedEffects.named(["wind"], 2.0).fluid_density == 60.0


def test_gravity_scale_makes_pybullet_fall_slower_than_meta_says_and_mujoco_models_it():
    effects = ConcealedEffects.named(["gravity_scale"], 1.0)
    assert effects.gravity_scale == pytest.approx(1 / 1.05)
    assert effects.truth(["gravity_scale"]) == [
        {"name": "gravity_scale", "parameters": {"gravity_scale": effects.gravity_scale}}
    ]
    throw = (1.5, -0.8, 0.5, 6.0, -4.0, 9.0)
    poses, _ = fly(effects, velocity=throw, frames=30)
    acceleration = np.diff(poses[:, 0, :3], 2, axis=0) / SETTINGS.dt**2
    np.testing.assert_allclose(
        acceleration, np.broadcast_to(np.array(SETTINGS.gravity) / 1.05, acceleration.shape), atol=1e-6
    )
    # MuJoCo's model of it: the scene's gravity times the scale; the same path as PyBullet's, not the plain one.
    rollouts = MujocoRollouts(_dataset_stub(), nthread=1)
    scaled = ContactParameters((0.5,), 0.0, None, None, effects=SceneEffects(gravity_scale=1 / 1.05))
    plain = ContactParameters((0.5,), 0.0, None, None)
    result = rollouts.simulate([scaled, plain], poses[None, 0], np.array([[throw]]), 29).poses[:, 0, :, 0]
    np.testing.assert_allclose(result[0, :, :3], poses[1:, 0, :3], atol=1e-6)
    assert np.abs(result[1, -1, :3] - poses[-1, 0, :3]).max() > 1e-3
    with pytest.raises(ContactbenchError, match="gravity scales"):
        SceneEffects(gravity_scale=0.0)


def test_the_library_models_gravity_scale_as_mujocos_gravity():
    from contactbench.diagnosis.library import Hypothesis, library

    effect = library(WIDTH)["gravity_scale"]
    hypothesis = Hypothesis(1).with_effect(effect)
    values = hypothesis.start()
    assert hypothesis.contact_parameters(values).effects.gravity_scale == 1.0  # starts switched off
    values[-1] = 0.95
    assert hypothesis.contact_parameters(values).effects.gravity_scale == pytest.approx(0.95)


def test_effects_outside_the_library_do_what_they_say_and_have_no_library_name():
    from contactbench.diagnosis.library import library
    from contactbench.generation.effects import OUTSIDE_LIBRARY

    assert not set(OUTSIDE_LIBRARY) & set(library(WIDTH))
    # Coriolis in free flight: v_{t+1} - v_t = dt (g - 2 Omega z x v_t), semi-implicit Euler as PyBullet steps.
    effects = ConcealedEffects.named(["coriolis"], 1.0)
    _, velocities = fly(effects, velocity=(2.0, 1.0, 0.0, 0.0, 0.0, 0.0))
    dv = np.diff(velocities[:, 0, :3], axis=0) / SETTINGS.dt - SETTINGS.gravity
    v = velocities[:-1, 0, :3]
    expected = -2 * effects.coriolis * np.cross([0.0, 0.0, 1.0], v)
    np.testing.assert_allclose(dv, expected, atol=1e-9)
    assert np.abs(dv).max() > 1.0
    # The floor's effects act only in contact: in the air the flight is the plain one.
    plain, _ = fly(ConcealedEffects(), velocity=(2.0, 1.0, 0.0, 0.0, 0.0, 0.0))
    for name in ("floor_viscosity", "floor_centring"):
        flown, _ = fly(ConcealedEffects.named([name], 2.0), velocity=(2.0, 1.0, 0.0, 0.0, 0.0, 0.0))
        np.testing.assert_array_equal(flown, plain)
    # On the floor, both slow a cube sliding away from the floor's centre; in the air above it they did nothing.
    start = np.array([[0.3, 0.0, WIDTH / 2, 1.0, 0.0, 0.0, 0.0]])

    def slide(effects):
        with BulletScene(CUBE, SPEC, SETTINGS, effects) as scene:
            return scene.simulate(start, np.array([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]]), 60)[0][-1, 0, 0]

    for name in ("floor_viscosity", "floor_centring"):
        assert slide(ConcealedEffects.named([name])) < slide(ConcealedEffects()) - 0.01, name


def test_spin_damping_slows_a_free_spin_at_its_rate_and_leaves_the_flight_alone():
    effects = ConcealedEffects.named(["spin_damping"], 1.0)
    spin = (2.0, 0.0, 0.0, 3.0, -4.0, 5.0)
    _, velocities = fly(effects, velocity=spin)
    _, plain_velocities = fly(ConcealedEffects(), velocity=spin)
    # a cube's inertia is isotropic: d w / dt = -rate w, integrated as PyBullet steps (semi-implicit Euler)
    ratio = np.linalg.norm(velocities[1:, 0, 3:], axis=-1) / np.linalg.norm(velocities[:-1, 0, 3:], axis=-1)
    np.testing.assert_allclose(ratio, 1 - effects.spin_damping * SETTINGS.dt, rtol=1e-6)
    np.testing.assert_allclose(velocities[..., :3], plain_velocities[..., :3], atol=1e-9)
    np.testing.assert_allclose(
        plain_velocities[:, 0, 3:], np.broadcast_to(spin[3:], plain_velocities[:, 0, 3:].shape), atol=1e-9
    )
