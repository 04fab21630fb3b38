"""The Drake engine: free flight, resting contact, parameters, its SDFormat scene file and batched rollouts."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

pytest.importorskip("pydrake")

from test_mujoco_sim import GRAVITY, box, scene  # noqa: E402 (after the skip: nothing here runs without Drake)

from contactbench import kinematics, rotations  # noqa: E402
from contactbench.errors import ContactbenchError, NotApplicable  # noqa: E402
from contactbench.models.sysid.search_space import search_space  # noqa: E402
from contactbench.sim.articulation import Articulation  # noqa: E402
from contactbench.sim.drake_engine import DrakeEngine, DrakeWorld  # noqa: E402
from contactbench.sim.drake_scene import DrakeParameters  # noqa: E402

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


def test_the_engine_takes_multi_body_and_hinged_scenes_and_refuses_non_convex_pieces_in_one_line():
    """Drake 1.51.1 crashes at random in body-body contact during searches (see the module docstring): its tosses
    always run in worker processes, where a crash costs only the tosses it hit (tests/test_stepped.py)."""
    assert not DrakeWorld.in_process
    ENGINE.rollouts(two_bodies()).close()
    ENGINE.rollouts(hinged_pair()).close()
    meta = copy.deepcopy(two_bodies().meta)
    meta["version"] = 2
    meta["bodies"][1]["pieces"] = [meta["bodies"][1]["mesh"]]
    with pytest.raises(NotApplicable, match=r"^the Drake engine .*; test-scene has non-convex bodies \(pieces\) "):
        ENGINE.rollouts(dataclasses.replace(two_bodies(), meta=meta))


# ---------------------------------------------------------------- hinges

BAR = box([-0.05, -0.025, -0.025], [0.05, 0.025, 0.025])  # the real elbow's 10 x 5 x 5 cm bars


def hinged_pair(
    damping: float = 0.0, friction: float = 0.0, parent_anchor=(-0.035, 0.06, 0.0), child_anchor=(-0.035, 0.0, 0.0)
):
    """Two bars on a hinge along their y axis; by default as the real elbow: the child beside the parent, turning
    about an axle through both near one end."""
    dataset = scene([BAR, BAR], dt=0.01)
    meta = copy.deepcopy(dataset.meta)
    meta["version"] = 2
    meta["joints"] = [
        {
            "name": "elbow",
            "type": "hinge",
            "parent": "body0",
            "child": "body1",
            "parent_anchor": list(parent_anchor),
            "child_anchor": list(child_anchor),
            "axis": [0.0, 1.0, 0.0],
            "damping": damping,
            "friction": friction,
        }
    ]
    return dataclasses.replace(dataset, meta=meta)


PAIR_PARAMETERS = DrakeParameters((0.4, 0.4), 0.6, 1e4, 1.0)


def toss_pair(dataset, parameters=PAIR_PARAMETERS, angle=0.4, rate=5.0, height=30.0, n_steps=100, substeps=1):
    """The pair tossed spinning, the child turning about the hinge: start poses and velocities, and what Drake gives."""
    joint = dataset.joints[0]
    parent = np.r_[0.0, 0.0, height, START_ORIENTATION]
    parent_velocity = np.r_[0.5, 0.2, 2.0, 1.0, -2.0, 3.0]
    child, child_velocity = kinematics.hinge_child(parent, parent_velocity, joint, np.array(angle), np.array(rate))
    poses0, velocities0 = np.stack([parent, child]), np.stack([parent_velocity, child_velocity])
    world = DrakeWorld(dataset, substeps)
    return world, poses0, velocities0, world.toss(parameters, poses0, velocities0, n_steps)


def centre_of_mass(dataset, poses, velocities):
    """The pair's centre of mass and its velocity, from each bar's mesh-frame pose and world velocity."""
    com, _ = dataset.inertial(0)  # both bars: the same mesh and mass
    lever = rotations.rotate(poses[..., 3:], com)
    return (poses[..., :3] + lever).mean(axis=-2), (velocities[..., :3] + np.cross(velocities[..., 3:], lever)).mean(-2)


def test_a_hinged_pair_in_free_flight_falls_at_its_centre_of_mass_and_keeps_its_hinge():
    dataset = hinged_pair()
    world, poses0, velocities0, (poses, velocities) = toss_pair(dataset)
    joint = dataset.joints[0]
    assert np.isfinite(poses).all()
    # The hinge is exact in every frame: the anchors coincide and the relative turn is about the axis alone.
    parent_anchor = kinematics.hinge_anchor(poses[:, 0], joint)
    child_anchor = kinematics.world_vertices(poses[:, 1], joint.child_anchor[None])[:, 0]
    assert np.abs(parent_anchor - child_anchor).max() < 1e-6
    relative = rotations.multiply(rotations.conjugate(poses[:, 0, 3:]), poses[:, 1, 3:])
    assert np.abs(np.cross(relative[:, 1:], joint.axis)).max() < 1e-9
    # What the world reports is Drake's own kinematics of the last state.
    simulation = world._simulation(PAIR_PARAMETERS)
    context = simulation.plant.GetMyContextFromRoot(simulation.simulator.get_context())
    for k in range(2):
        body = simulation.plant.GetBodyByName(f"body{k}")
        pose = simulation.plant.EvalBodyPoseInWorld(context, body)
        velocity = simulation.plant.EvalBodySpatialVelocityInWorld(context, body)
        np.testing.assert_allclose(pose.translation(), poses[-1, k, :3], atol=1e-12)
        np.testing.assert_allclose(pose.rotation().matrix(), rotations.to_matrix(poses[-1, k, 3:]), atol=1e-12)
        np.testing.assert_allclose(velocity.translational(), velocities[-1, k, :3], atol=1e-12)
        np.testing.assert_allclose(velocity.rotational(), velocities[-1, k, 3:], atol=1e-12)
    # Gravity is the only external force: the centre of mass falls on the parabola, up to Drake's first-order step
    # (ten times smaller steps, ten times smaller errors; a wrong hinge angle, anchor or inertia would leave an error
    # that does not shrink).
    errors = []
    for substeps in (1, 10):
        _, poses0, velocities0, (poses, velocities) = toss_pair(dataset, substeps=substeps)
        com0, com_velocity0 = centre_of_mass(dataset, poses0, velocities0)
        coms, com_velocities = centre_of_mass(dataset, poses, velocities)
        t = 0.01 * np.arange(1, len(coms) + 1)[:, None]
        errors.append(
            (
                np.abs(coms - (com0 + com_velocity0 * t + GRAVITY * t**2 / 2)).max(),
                np.abs(com_velocities - (com_velocity0 + GRAVITY * t)).max(),
            )
        )
    (position_error, velocity_error), (fine_position_error, fine_velocity_error) = errors
    assert fine_position_error < 1e-2 and 8 < position_error / fine_position_error < 12
    assert fine_velocity_error < 1e-3 and 8 < velocity_error / fine_velocity_error < 12


def test_joint_damping_and_friction_slow_the_relative_spin():
    rates = {}
    for name, damping, friction in (("free", 0.0, 0.0), ("damped", 0.002, 0.0), ("rubbing", 0.0, 0.01)):
        dataset = hinged_pair(damping, friction)
        _, _, _, (poses, velocities) = toss_pair(dataset, n_steps=50)
        _, rate = kinematics.hinge_coordinates(
            poses[:, 0], velocities[:, 0], poses[:, 1], velocities[:, 1], dataset.joints[0]
        )
        rates[name] = np.abs(rate)
    assert rates["free"].min() > 2.0  # the free hinge keeps turning
    # Damping takes the rate down smoothly; friction stops the joint and holds it.
    assert np.all(np.diff(rates["damped"]) < 0) and rates["damped"][-1] < 0.1 * rates["free"][-1]
    assert rates["rubbing"][-1] < 0.05 and rates["rubbing"][-1] < 0.02 * rates["free"][-1]


def test_articulation_parameters_round_trip_the_search_space_and_act():
    space = search_space("drake", 2, 1)
    assert {"joint_damping_0", "joint_friction_0", "inertia_scale"} <= set(space.names)
    candidate = space.to_parameters(space.parametrization(seed=0).value)
    assert candidate.articulation is not None
    assert space.from_vector(space.to_vector(candidate)) == candidate
    fitted = dataclasses.replace(candidate, articulation=Articulation((0.004,), (0.0,), 1.5))
    assert space.from_vector(space.to_vector(fitted)) == fitted and hash(fitted) == hash(
        space.from_vector(space.to_vector(fitted))
    )
    # The articulation replaces the scene's joint values: damping in it acts like damping recorded in the scene.
    dataset = hinged_pair()
    recorded = toss_pair(hinged_pair(0.004), n_steps=30)[-1]
    identified = toss_pair(
        dataset, dataclasses.replace(PAIR_PARAMETERS, articulation=Articulation((0.004,), (0.0,))), n_steps=30
    )[-1]
    np.testing.assert_array_equal(identified[0], recorded[0])
    scaled = toss_pair(
        dataset, dataclasses.replace(PAIR_PARAMETERS, articulation=Articulation((0.0,), (0.0,), 1.5)), n_steps=30
    )[-1]
    assert not np.allclose(scaled[0], toss_pair(dataset, n_steps=30)[-1][0])


def test_folding_links_collide_and_a_hinged_scene_file_simulates_as_the_world(tmp_path):
    """The SDFormat revolute joint carries the hinge's damping and friction; hinged links collide with each other."""
    # End to end on an axle beyond both bars' ends: the parent lies on the floor, the child stands up from the axle
    # and tips over towards it. Its inner edge catches on the parent's top edge long before it could fold flat
    # (angle ±π, where the two bars would overlap).
    dataset = hinged_pair(parent_anchor=(0.08, 0.0, 0.0), child_anchor=(-0.08, 0.0, 0.0))
    parameters = dataclasses.replace(PAIR_PARAMETERS, articulation=Articulation((0.001,), (0.002,), 1.2))
    files = ENGINE.scene_files(dataset, parameters, substeps=2)
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert '<joint name="hinge0" type="revolute">' in files["scene.sdf"]
    parent = np.r_[0.0, 0.0, 0.025, 1.0, 0.0, 0.0, 0.0]
    child, child_velocity = kinematics.hinge_child(parent, np.zeros(6), dataset.joints[0], -np.pi / 2, -1.0)
    poses0, velocities0 = np.stack([parent, child]), np.stack([np.zeros(6), child_velocity])
    built = DrakeWorld(dataset, 2).toss(parameters, poses0, velocities0, 100)
    parsed = DrakeWorld(dataset, 2, scene_file=tmp_path / "scene.sdf").toss(parameters, poses0, velocities0, 100)
    for from_file, from_world in zip(parsed, built):
        np.testing.assert_allclose(from_file, from_world, rtol=0, atol=1e-9)
    poses, velocities = built
    angles, _ = kinematics.hinge_coordinates(
        poses[:, 0], velocities[:, 0], poses[:, 1], velocities[:, 1], dataset.joints[0]
    )
    assert np.isfinite(poses).all() and np.abs(angles).max() < 2.0 and angles[-1] < -np.pi / 2
    assert poses[-1, 1, 2] > 0.09  # still up, leaning on the parent
    np.testing.assert_allclose(velocities[-1], 0.0, atol=1e-3)


def test_a_toss_where_the_discrete_solver_fails_goes_on_at_a_finer_step():
    """Untuned Drake on real elbow toss 190 (val): TAMSI fails to converge at the recordings' step within the first
    quarter second; the world goes on from the last frame at a finer step, so the toss is scored, not lost."""
    from contactbench.config import CONFIG_DIR
    from contactbench.protocol import make_context
    from contactbench.recordings import read_recordings
    from contactbench.sim.drake_engine import FALLBACK_REFINEMENTS

    elbow = read_recordings(CONFIG_DIR.parent / "assets" / "contactnets_elbow", ["val"])
    split = elbow.split("val")
    toss = int(np.flatnonzero(split.extras["source_index"] == 190)[0])
    context = make_context(split.select([toss]), elbow.dt, 6)
    world = DrakeWorld(elbow.scene, 1)
    parameters = ENGINE.default_parameters(2)
    steps = 60
    _, _, failed_at = world._simulation(parameters).toss(context.poses[0, -1], context.velocities[0, -1], steps)
    assert failed_at is not None and failed_at < steps  # the solver does fail here at the recordings' step
    poses, velocities = world.toss(parameters, context.poses[0, -1], context.velocities[0, -1], steps)
    assert np.isfinite(poses).all() and np.isfinite(velocities).all()
    gap = np.linalg.norm(
        kinematics.hinge_anchor(poses[:, 0], elbow.joints[0])
        - kinematics.world_vertices(poses[:, 1], elbow.joints[0].child_anchor[None])[:, 0],
        axis=-1,
    )
    assert gap.max() < 1e-9
    finest = world._simulation(parameters, FALLBACK_REFINEMENTS[-1])
    assert finest.frame_steps == FALLBACK_REFINEMENTS[-1]
