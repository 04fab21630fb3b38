"""The Drake engine: free flight, resting contact, parameters, its SDFormat scene file and batched rollouts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("pydrake")

from test_mujoco_sim import GRAVITY, box, scene  # noqa: E402 (after the skip: nothing here runs without Drake)

from contactbench import rotations  # noqa: E402
from contactbench.errors import ContactbenchError, NotApplicable  # noqa: E402
from contactbench.sim.drake_engine import DrakeEngine, DrakeParameters, DrakeWorld  # noqa: E402

ENGINE = DrakeEngine()
CUBE = box([-0.05] * 3, [0.05] * 3)
OFFSET_BOX = box([0.0, -0.02, 0.01], [0.1, 0.06, 0.05])  # centre of mass (0.05, 0.02, 0.03) in its mesh frame
STIFF = DrakeParameters(object_friction=(0.4,), floor_friction=0.6, point_stiffness=1e4, hunt_crossley_dissipation=1.0)
START_ORIENTATION = rotations.normalize(np.array([0.9, 0.1, -0.3, 0.2]))


def mechanical_energy(mass, inertia, com_velocity, world_angular_velocity, orientation, com_height) -> np.ndarray:
    rotation = rotations.to_matrix(orientation)
    world_inertia = rotation @ inertia @ np.swapaxes(rotation, -1, -2)
    spin = np.einsum("...i,...ij,...j->...", world_angular_velocity, world_inertia, world_angular_velocity)
    return 0.5 * mass * (com_velocity**2).sum(-1) + 0.5 * spin - mass * GRAVITY[2] * com_height


def fly(substeps: int, angular_velocity: np.ndarray, n_steps: int = 30):
    """An offset-centre-of-mass box tossed high: its com positions [n, 3], com start, start com velocity, the world
    angular momentum about the com [n, 3] and its start value."""
    dataset = scene([OFFSET_BOX], dt=0.01)
    com, inertia = dataset.inertial(0)
    com_velocity = np.array([0.7, -0.3, 2.0])
    lever = rotations.rotate(START_ORIENTATION, com)
    pose = np.r_[0.2, -0.1, 30.0, START_ORIENTATION]
    velocity = np.r_[com_velocity - np.cross(angular_velocity, lever), angular_velocity]  # of the mesh-frame origin
    poses, velocities = DrakeWorld(dataset, substeps).toss(STIFF, pose[None], velocity[None], n_steps)
    coms = poses[:, 0, :3] + rotations.rotate(poses[:, 0, 3:], com)
    rotation = rotations.to_matrix(poses[:, 0, 3:])
    momenta = np.einsum("tij,jk,tlk,tl->ti", rotation, inertia, rotation, velocities[:, 0, 3:])
    start_rotation = rotations.to_matrix(START_ORIENTATION)
    return coms, pose[:3] + lever, com_velocity, momenta, start_rotation @ inertia @ start_rotation.T @ angular_velocity


def test_free_flight_of_an_offset_centre_of_mass_follows_g_exactly_without_spin():
    substeps, n_steps, h = 2, 30, 0.005
    coms, com0, com_velocity, _, _ = fly(substeps, np.zeros(3), n_steps)
    steps = substeps * np.arange(1, n_steps + 1)[:, None]
    # Drake's discrete step is semi-implicit: v_n = v_0 + n h g, x_n = x_0 + h (v_1 + ... + v_n).
    np.testing.assert_allclose(
        coms, com0 + steps * h * com_velocity + h * h * GRAVITY * steps * (steps + 1) / 2, atol=1e-9
    )
    t = steps * h
    parabola = com0 + com_velocity * t + GRAVITY * t**2 / 2
    np.testing.assert_allclose(coms, parabola, atol=h * 9.81 * t.max() / 2 + 1e-9)  # the semi-implicit lag, h g t / 2


def test_spinning_free_flight_conserves_angular_momentum_to_first_order_in_the_step():
    spin = np.array([1.0, -2.0, 3.0])
    momentum_errors, com_errors = [], []
    for substeps in (1, 10):
        coms, com0, com_velocity, momenta, momentum0 = fly(substeps, spin)
        t = 0.01 * np.arange(1, len(coms) + 1)[:, None]
        com_errors.append(np.abs(coms - (com0 + com_velocity * t + GRAVITY * t**2 / 2)).max())
        momentum_errors.append(np.abs(momenta - momentum0).max() / np.linalg.norm(momentum0))
    # Drake's step is first order (explicit gyroscopic and centripetal terms): ten times smaller steps, ten times
    # smaller errors; a wrong velocity or inertia conversion would leave an error that does not shrink.
    assert momentum_errors[1] < 2e-3 and 8 < momentum_errors[0] / momentum_errors[1] < 12
    assert com_errors[1] < 2e-3 and 8 < com_errors[0] / com_errors[1] < 12


def test_dropped_cube_comes_to_rest_on_its_four_corners_without_gaining_energy():
    dataset = scene([CUBE], dt=0.01, floor_z=0.2)
    tilted = rotations.normalize(np.array([1.0, 0.1, 0.05, 0.0]))
    poses, velocities = DrakeWorld(dataset, 2).toss(
        STIFF, np.r_[0.0, 0.0, 0.5, tilted][None], np.array([[0.3, 0.0, 0.0, 0.0, 0.0, 1.0]]), 150
    )
    _, inertia = dataset.inertial(0)
    energy = mechanical_energy(
        0.37, inertia, velocities[:, 0, :3], velocities[:, 0, 3:], poses[:, 0, 3:], poses[:, 0, 2]
    )
    start = mechanical_energy(0.37, inertia, np.array([0.3, 0, 0]), np.array([0, 0, 1.0]), tilted, 0.5)
    assert np.isfinite(poses).all() and (energy <= start + 1e-9).all()  # the springs' energy is not counted
    np.testing.assert_allclose(velocities[-1, 0], 0.0, atol=1e-6)
    assert np.abs(rotations.to_matrix(poses[-1, 0, 3:])[2, 2]) > 1 - 1e-9  # flat on a face
    # Four corner contacts of stiffness k share the weight.
    np.testing.assert_allclose(poses[-1, 0, 2], 0.2 + 0.05 - 0.37 * 9.81 / (4 * 1e4), rtol=0, atol=1e-9)


def test_hydroelastic_cube_rests_on_the_floor():
    dataset = scene([CUBE], dt=0.01, floor_z=0.2)
    parameters = dataclasses.replace(STIFF, contact_model="hydroelastic", hydroelastic_modulus=1e6)
    poses, velocities = DrakeWorld(dataset, 1).toss(
        parameters, np.array([[0.0, 0.0, 0.25, 1.0, 0.0, 0.0, 0.0]]), np.zeros((1, 6)), 100
    )
    np.testing.assert_allclose(velocities[-1, 0], 0.0, atol=1e-6)
    assert 0.25 - 1e-3 < poses[-1, 0, 2] < 0.25


def test_parameters_round_trip_and_invalid_values_raise():
    parameters = ENGINE.from_values(
        {
            "object_friction_0": 0.2,
            "object_friction_1": 0.7,
            "floor_friction": 0.3,
            "point_stiffness": 2e4,
            "hunt_crossley_dissipation": 0.8,
        },
        2,
    )
    assert ENGINE.from_values(ENGINE.to_values(parameters), 2) == parameters
    assert hash(parameters) == hash(ENGINE.from_values(ENGINE.to_values(parameters), 2))
    names = {d.name for d in ENGINE.dimensions(2)}
    assert names == set(ENGINE.to_values(parameters))
    defaults = ENGINE.default_parameters(2)
    assert (defaults.floor_friction, defaults.point_stiffness, defaults.hunt_crossley_dissipation) == (0.5, 1e6, 50.0)
    for invalid in (
        {"floor_friction": -0.1},
        {"point_stiffness": 0.0},
        {"hunt_crossley_dissipation": np.inf},
        {"contact_model": "penalty"},
        {"hydroelastic_modulus": -1.0},
    ):
        with pytest.raises(ContactbenchError):
            dataclasses.replace(parameters, **invalid)
    with pytest.raises(ContactbenchError, match="object frictions"):
        DrakeWorld(scene([CUBE]), 1).toss(parameters, np.zeros((1, 7)), np.zeros((1, 6)), 1)


def two_bodies():
    return scene([CUBE, OFFSET_BOX], dt=0.01)


def stacked_start(n_tosses: int) -> tuple[np.ndarray, np.ndarray]:
    """Tosses of the offset box dropped onto the cube, the cube sliding."""
    poses = np.zeros((n_tosses, 2, 7))
    poses[:, 0] = [0.0, 0.0, 0.06, 1.0, 0.0, 0.0, 0.0]
    poses[:, 1] = [-0.05, -0.02, 0.25, 1.0, 0.0, 0.0, 0.0]  # above the cube
    velocities = np.zeros((n_tosses, 2, 6))
    velocities[:, 0, 0] = np.linspace(0.0, 0.5, n_tosses)
    velocities[:, 1, 3:] = [0.5, 0.3, 2.0]
    return poses, velocities


TWO_BODY_PARAMETERS = DrakeParameters((0.3, 0.8), 0.5, 3e4, 2.0)


def test_scene_file_parsed_by_drake_simulates_as_the_world(tmp_path):
    dataset = two_bodies()
    files = ENGINE.scene_files(dataset, TWO_BODY_PARAMETERS, substeps=2)
    assert list(files)[0] == "scene.sdf"
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    poses0, velocities0 = stacked_start(1)
    parsed = DrakeWorld(dataset, 2, scene_file=tmp_path / "scene.sdf").toss(
        TWO_BODY_PARAMETERS, poses0[0], velocities0[0], 60
    )
    built = DrakeWorld(dataset, 2).toss(TWO_BODY_PARAMETERS, poses0[0], velocities0[0], 60)
    assert np.isfinite(built[0]).all()
    for from_file, from_world in zip(parsed, built):
        np.testing.assert_allclose(from_file, from_world, rtol=0, atol=1e-9)


def test_two_bodies_collide_and_stay_stacked():
    poses0, velocities0 = stacked_start(1)
    poses, _ = DrakeWorld(two_bodies(), 2).toss(TWO_BODY_PARAMETERS, poses0[0], velocities0[0], 200)
    assert np.isfinite(poses).all()
    # The box's lowest face (0.01 above its mesh origin) stays on the cube's top at z = 0.1, not through it; one
    # contact point per pair of hulls lets it rock there (see the module docstring).
    assert 0.1 - 0.01 - 2e-3 < poses[-1, 1, 2] < 0.1
    assert 0.05 - 1e-3 < poses[-1, 0, 2] < 0.05


def test_worker_processes_give_bit_identical_results():
    dataset = scene([OFFSET_BOX], dt=0.01)
    poses0, velocities0 = stacked_start(3)
    poses0, velocities0 = poses0[:, 1:], velocities0[:, 1:]  # the box alone, dropped spinning
    other = dataclasses.replace(STIFF, point_stiffness=1e3, object_friction=(0.1,))
    results = []
    for nthread in (1, 2):
        rollouts = ENGINE.rollouts(dataset, nthread=nthread, substeps=1)
        try:
            results.append(rollouts.simulate([STIFF, other], poses0, velocities0, 40))
        finally:
            rollouts.close()
    assert np.isfinite(results[0].poses).all()
    np.testing.assert_array_equal(results[0].poses, results[1].poses)
    np.testing.assert_array_equal(results[0].velocities, results[1].velocities)
    # Parameters changed between tosses in one world: the second set's tosses differ from the first's.
    assert not np.allclose(results[0].poses[0], results[0].poses[1])


def test_the_engine_refuses_multi_body_scenes_as_not_applicable():
    """Drake 1.51.1 crashed at random in body-body contact during searches (see the module docstring): the engine
    skips such a job with one line instead of killing a sweep."""
    with pytest.raises(NotApplicable, match="single-body scenes; .* has 2 bodies"):
        ENGINE.rollouts(two_bodies())
