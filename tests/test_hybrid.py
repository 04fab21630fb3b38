"""Tests of the hybrid contact model: LCP against hand results, inverse dynamics, features, rollout, Lightning."""

from __future__ import annotations

import numpy as np
import pybullet
import pytest
import pytorch_lightning as pl
import torch
from conftest import cube_mesh, falling_cubes
from pytorch_lightning.callbacks import EarlyStopping, ModelCheckpoint

from contactbench import rotations
from contactbench.models.hybrid import (
    ContactSettings,
    HybridContactModel,
    HybridDataModule,
    HybridModule,
    SingleBodyError,
    compare_with_bullet_contacts,
    dynamics,
    features,
    inverse,
    lcp,
)
from contactbench.models.hybrid.dynamics import State
from contactbench.models.hybrid.module import training_arrays
from contactbench.models.selection import ValRollouts
from contactbench.protocol import make_context
from contactbench.scene import FORMAT, VERSION, Recordings, Split

MASS = 0.37
WIDTH = 0.1
HALF = WIDTH / 2
DT = 0.01
G = 9.81


def cube_recordings(splits: dict[str, Split] | None = None) -> Recordings:
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "name": "hybrid-test",
        "dt": DT,
        "gravity": [0.0, 0.0, -G],
        "floor_z": 0.0,
        "bodies": [{"name": "cube", "mesh": "meshes/cube.obj", "mass": MASS}],
        "splits": {name: f"{name}.npz" for name in (splits or {"train": None})},
    }
    return Recordings(meta=meta, meshes={"meshes/cube.obj": cube_mesh(WIDTH)}, splits=splits or {})


@pytest.fixture
def scene() -> dynamics.SingleBodyScene:
    return dynamics.single_body_scene(cube_recordings())


def make_state(position, orientation=(1.0, 0.0, 0.0, 0.0), linear=(0.0, 0.0, 0.0), angular=(0.0, 0.0, 0.0)) -> State:
    return State(*(np.asarray(value, dtype=float)[None] for value in (position, orientation, linear, angular)))


def bottom_vertices(scene: dynamics.SingleBodyScene) -> np.ndarray:
    return scene.body.vertices[:, 2] < 0


# ---------------------------------------------------------------- LCP


@pytest.mark.parametrize("solver", ["pgs", "lemke"])
def test_resting_cube_normal_impulses_cancel_gravity(scene, solver):
    state = make_state([0.3, -0.2, HALF])
    after, impulses = lcp.frictionless_step(state, scene, np.zeros((1, 6)), ContactSettings(solver=solver))
    bottom = bottom_vertices(scene)
    assert impulses[0, bottom].sum() == pytest.approx(MASS * G * DT, rel=1e-9)
    assert np.all(impulses[0, ~bottom] == 0.0)
    assert np.abs(after.linear).max() < 1e-9 and np.abs(after.angular).max() < 1e-9
    np.testing.assert_allclose(after.position, state.position, atol=1e-11)


@pytest.mark.parametrize("restitution", [0.0, 0.5])
def test_dropping_cube_stops_or_bounces_by_restitution(scene, restitution):
    speed = 1.0
    state = make_state([0.0, 0.0, HALF], linear=[0.0, 0.0, -speed])
    after, impulses = lcp.frictionless_step(state, scene, np.zeros((1, 6)), ContactSettings(restitution=restitution))
    approach = speed + G * DT  # normal speed after gravity, before contact
    assert after.linear[0, 2] == pytest.approx(restitution * approach, abs=1e-9)
    assert impulses.sum() == pytest.approx(MASS * (1 + restitution) * approach, rel=1e-9)


def test_fast_cube_lands_on_the_floor_instead_of_tunnelling(scene):
    gap = 0.003
    state = make_state([0.0, 0.0, HALF + gap], linear=[0.0, 0.0, -2.0])  # would travel 20 mm in one step
    after, _ = lcp.frictionless_step(state, scene, np.zeros((1, 6)), ContactSettings())
    assert dynamics.vertex_gaps(after, scene).min() == pytest.approx(0.0, abs=1e-10)
    assert after.linear[0, 2] == pytest.approx(-gap / DT, rel=1e-9)


def test_penetration_is_removed_at_the_stabilisation_rate(scene):
    depth, beta = 0.002, 0.3
    state = make_state([0.0, 0.0, HALF - depth])
    after, _ = lcp.frictionless_step(state, scene, np.zeros((1, 6)), ContactSettings(stabilisation=beta))
    assert dynamics.vertex_gaps(after, scene).min() == pytest.approx(-(1 - beta) * depth, abs=1e-10)


@pytest.mark.parametrize("solver", ["pgs", "lemke"])
def test_no_contact_gives_zero_impulses(scene, solver):
    state = make_state([0.0, 0.0, 0.5], linear=[1.0, 0.0, -1.0], angular=[3.0, 1.0, 0.0])
    after, impulses = lcp.frictionless_step(state, scene, np.zeros((1, 6)), ContactSettings(solver=solver))
    assert np.all(impulses == 0.0)
    np.testing.assert_allclose(after.linear, [[1.0, 0.0, -1.0 - G * DT]])


def random_contact_states(count: int, seed: int) -> State:
    """Cubes in random orientations with their lowest vertex within +-3 mm of the floor, moving at random."""
    rng = np.random.default_rng(seed)
    orientation = rotations.uniform_random(rng, count)
    lowest = rotations.rotate(orientation[:, None], cube_mesh(WIDTH).vertices)[..., 2].min(axis=-1)
    position = np.concatenate(
        [rng.uniform(-1, 1, (count, 2)), (-lowest + rng.uniform(-0.003, 0.003, count))[:, None]], axis=-1
    )
    return State(position, orientation, rng.uniform(-1, 1, (count, 3)), rng.uniform(-8, 8, (count, 3)))


def test_lcp_solutions_are_complementary_and_solvers_agree(scene):
    states = random_contact_states(40, seed=1)
    settings = ContactSettings()
    linear, angular = dynamics.unconstrained_velocities(states, scene)
    offsets = dynamics.vertex_offsets(states.orientation, scene.body)
    gaps = dynamics.vertex_gaps(states, scene)
    least = np.where(gaps >= 0, -gaps, -settings.stabilisation * gaps) / DT
    free = dynamics.normal_velocities(offsets, linear, angular)
    matrix = dynamics.delassus(states.orientation, offsets, scene.body)
    candidates = lcp.contact_candidates(states, scene, linear, angular, settings)
    wrenches = {}
    for solver in ("pgs", "lemke"):
        impulses = lcp.solve_at_candidates(matrix, free - least, candidates, solver)
        slack = np.einsum("bij,bj->bi", matrix, impulses) + free - least  # w = M z + q
        scale = np.abs(free - least).max()
        assert impulses.min() >= 0.0
        assert np.where(candidates, slack, 0.0).min() > -1e-7 * scale
        assert np.abs(impulses * slack).max() < 1e-7 * scale * np.abs(impulses).max()
        assert np.all(impulses[~candidates] == 0.0)
        wrenches[solver] = dynamics.normal_wrench(offsets, impulses)
    assert np.abs(wrenches["pgs"]).max() > 0  # the random states do make contact
    np.testing.assert_allclose(wrenches["pgs"], wrenches["lemke"], atol=1e-8 * np.abs(wrenches["lemke"]).max())


def test_lemke_matches_a_hand_solved_lcp():
    # z1 active, z2 inactive: w1 = 2 z1 + z2 - 2 = 0 -> z1 = 1; w2 = z1 + 2 z2 + 1 = 2 > 0.
    solution = lcp.solve_lemke(np.array([[2.0, 1.0], [1.0, 2.0]]), np.array([-2.0, 1.0]))
    np.testing.assert_allclose(solution, [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(
        lcp.solve_pgs(np.array([[[2.0, 1.0], [1.0, 2.0]]]), np.array([[-2.0, 1.0]]))[0], [1.0, 0.0], atol=1e-9
    )


def test_sliding_cube_decelerates_as_the_hand_result(scene):
    """Coulomb friction mu m g at the floor: v_n = v_0 - n mu g dt, no rotation, front edge carries (1 + mu h/a)/2 of
    the weight."""
    mu, speed, steps = 0.4, 1.0, 20
    state = make_state([0.0, 0.0, HALF], linear=[speed, 0.0, 0.0])
    force = -mu * MASS * G
    # The friction force acts in the floor plane, h = HALF below the CoM: its torque about the CoM is (0, h |F|, 0).
    friction = np.array([[force, 0.0, 0.0, 0.0, -HALF * force, 0.0]]) * DT
    positions = [state.position[0, 0]]
    for _ in range(steps):
        state, impulses = lcp.frictionless_step(state, scene, friction, ContactSettings())
        positions.append(state.position[0, 0])
    velocities = speed - mu * G * DT * np.arange(1, steps + 1)
    assert state.linear[0, 0] == pytest.approx(velocities[-1], rel=1e-9)
    np.testing.assert_allclose(np.diff(positions), DT * velocities, rtol=1e-9)
    assert np.abs(state.angular).max() < 1e-8
    assert state.position[0, 2] == pytest.approx(HALF, abs=1e-9)
    front = scene.body.vertices[:, 0] > 0
    assert impulses[0, front].sum() / (MASS * G * DT) == pytest.approx((1 + mu) / 2, rel=1e-7)  # h / a = 1 for a cube


def kinetic_energy(
    state: State, scene: dynamics.SingleBodyScene, linear: np.ndarray, angular: np.ndarray
) -> np.ndarray:
    inertia = dynamics.world_inertia(state.orientation, scene.body)
    return 0.5 * MASS * np.sum(linear**2, axis=-1) + 0.5 * np.einsum("bi,bij,bj->b", angular, inertia, angular)


def test_dissipative_friction_stops_a_sliding_cube_without_reversing_it(scene):
    """Hand case: cube sliding at v on its face, friction impulse -j along x at the CoM. The impulse that stops it is
    m v; a larger prediction is cut to that, a smaller one passes, a push along the motion is dropped."""
    speed = 0.2
    state = make_state([0.0, 0.0, HALF], linear=[speed, 0.0, 0.0])
    stopping = MASS * speed
    for predicted, expected in ((3.0 * stopping, stopping), (0.4 * stopping, 0.4 * stopping), (-stopping, 0.0)):
        friction = np.array([[-predicted, 0.0, 0.0, 0.0, 0.0, 0.0]])
        kept = lcp.dissipative_friction(state, scene, friction)
        np.testing.assert_allclose(kept, [[-expected, 0.0, 0.0, 0.0, 0.0, 0.0]], rtol=1e-12, atol=1e-15)
        after, _ = lcp.frictionless_step(state, scene, kept, ContactSettings())
        assert after.linear[0, 0] == pytest.approx(speed - expected / MASS, abs=1e-12)
        assert after.linear[0, 0] >= -1e-12


def test_dissipative_friction_keeps_a_resting_cube_at_rest(scene):
    """At rest only gravity moves the body (straight down); tangential friction would set it sliding, so none is
    kept."""
    state = make_state([0.1, 0.0, HALF])
    friction = np.array([[0.02, -0.01, 0.0, 0.003, 0.001, -0.002]])
    np.testing.assert_array_equal(lcp.dissipative_friction(state, scene, friction), np.zeros((1, 6)))
    after, _ = lcp.frictionless_step(state, scene, lcp.dissipative_friction(state, scene, friction), ContactSettings())
    assert np.abs(after.linear).max() < 1e-9 and np.abs(after.angular).max() < 1e-9  # PGS tolerance


def test_dissipative_friction_never_adds_kinetic_energy(scene):
    states = random_contact_states(200, seed=4)
    rng = np.random.default_rng(5)
    friction = rng.normal(0.0, 1.0, (200, 6)) * np.array([0.05, 0.05, 0.05, 0.003, 0.003, 0.003])
    kept = lcp.dissipative_friction(states, scene, friction)
    linear, angular = dynamics.unconstrained_velocities(states, scene)
    linear_change, angular_change = dynamics.velocity_change(states.orientation, kept, scene.body)
    before = kinetic_energy(states, scene, linear, angular)
    after = kinetic_energy(states, scene, linear + linear_change, angular + angular_change)
    assert np.all(after <= before + 1e-12)
    scale = np.linalg.norm(kept, axis=-1) / np.linalg.norm(friction, axis=-1)
    assert (
        np.all(scale <= 1.0 + 1e-12)
        and (scale == 0.0).any()
        and (scale > 0.99).any()
        and ((scale > 0.01) & (scale < 0.99)).any()
    )


# ---------------------------------------------------------------- inverse dynamics


def window_split(
    state: State, next_linear: np.ndarray, next_angular: np.ndarray, scene: dynamics.SingleBodyScene
) -> Split:
    """Frames t-1, t, t+1 of one trajectory whose backward differences are the given velocities."""
    before = State(
        state.position - DT * state.linear,
        rotations.multiply(rotations.from_rotation_vector(-state.angular * DT), state.orientation),
        state.linear,
        state.angular,
    )
    after = dynamics.integrate(state, next_linear, next_angular, DT)
    poses = np.stack([dynamics.poses_from_states(s, scene.body) for s in (before, state, after)], axis=1)
    return Split(poses[:, :, None], np.full(len(poses), 3))


def applied_impulse(
    state: State, scene: dynamics.SingleBodyScene, normal: np.ndarray, friction_forces: np.ndarray, torsion: float
):
    """Body impulse of normal impulses [V] and tangential impulses [V, 3] at the vertices, plus a torsional impulse."""
    offsets = dynamics.vertex_offsets(state.orientation, scene.body)[0]
    normal_part = dynamics.normal_wrench(offsets[None], normal[None])[0]
    friction_part = np.concatenate(
        [friction_forces.sum(axis=0), np.cross(offsets, friction_forces).sum(axis=0) + [0.0, 0.0, torsion]]
    )
    return normal_part, friction_part


@pytest.mark.parametrize(
    "orientation",
    [(1.0, 0.0, 0.0, 0.0), rotations.from_axis_angle(np.array([0.0, 0.0, 1.0]), 0.7)],
)
def test_inverse_dynamics_recovers_known_face_contact_impulses(scene, orientation):
    """Sliding and spinning on a face: normal impulses, friction proportional to them along one direction, torsion."""
    state = make_state([0.1, 0.2, HALF], orientation, linear=[0.8, 0.3, 0.0], angular=[0.0, 0.0, 2.0])
    bottom = bottom_vertices(scene)
    normal = np.where(bottom, [0.2, 0.0, 0.7, 0.0, 1.1, 0.0, 0.4, 0.0], 0.0) * MASS * G * DT
    direction = np.array([-0.8, -0.3, 0.0]) / np.hypot(0.8, 0.3)
    friction_forces = 0.6 * normal[:, None] * direction
    normal_part, friction_part = applied_impulse(state, scene, normal, friction_forces, torsion=-1e-4)
    linear, angular = dynamics.unconstrained_velocities(state, scene)
    change = dynamics.velocity_change(state.orientation, (normal_part + friction_part)[None], scene.body)
    split = window_split(state, linear + change[0], angular + change[1], scene)
    transitions = inverse.transitions_from_split(split, scene, ContactSettings())
    np.testing.assert_allclose(transitions.impulse[0], normal_part + friction_part, atol=1e-12)
    np.testing.assert_allclose(transitions.normal_wrench[0], normal_part, atol=1e-12)
    np.testing.assert_allclose(transitions.friction[0], friction_part, atol=1e-12)
    assert transitions.in_contact[0]


def test_inverse_dynamics_recovers_a_corner_impact_per_vertex(scene):
    # Corner-down cube: the body diagonal (1, 1, 1) turned onto -z; the lowest corner touches the floor.
    axis = np.cross([1.0, 1.0, 1.0], [0.0, 0.0, -1.0])
    angle = np.arccos(-1.0 / np.sqrt(3.0))
    orientation = rotations.from_axis_angle(axis, angle)
    height = HALF * np.sqrt(3.0)
    state = make_state([0.0, 0.0, height], orientation, linear=[0.5, 0.0, -1.0], angular=[1.0, -2.0, 0.5])
    corner = np.argmin(dynamics.vertex_gaps(state, scene)[0])
    normal = np.zeros(8)
    normal[corner] = 0.3
    friction_forces = np.zeros((8, 3))
    friction_forces[corner] = [-0.05, 0.02, 0.0]
    normal_part, friction_part = applied_impulse(state, scene, normal, friction_forces, torsion=0.0)
    linear, angular = dynamics.unconstrained_velocities(state, scene)
    change = dynamics.velocity_change(state.orientation, (normal_part + friction_part)[None], scene.body)
    transitions = inverse.transitions_from_split(
        window_split(state, linear + change[0], angular + change[1], scene), scene, ContactSettings()
    )
    np.testing.assert_allclose(transitions.normal[0], normal, atol=1e-12)
    np.testing.assert_allclose(transitions.friction[0], friction_part, atol=1e-12)


def test_free_flight_gives_a_zero_contact_wrench():
    recordings = falling_cubes(n_trajectories=3, n_frames=12)
    scene = dynamics.single_body_scene(recordings)
    transitions = inverse.transitions_from_split(recordings.split("train"), scene, ContactSettings())
    assert len(transitions.frame) == 3 * 10
    assert np.abs(transitions.impulse).max() < 1e-10
    assert not transitions.in_contact.any()
    assert np.all(transitions.normal == 0.0)


def bullet_cube_tosses(friction: float, tosses: int = 3, frames: int = 90) -> Recordings:
    """A few PyBullet tosses of the test cube (one engine step per frame) with its contact forces."""
    client = pybullet.connect(pybullet.DIRECT)
    rng = np.random.default_rng(3)
    try:
        pybullet.setPhysicsEngineParameter(fixedTimeStep=DT, numSubSteps=0, physicsClientId=client)
        pybullet.setGravity(0.0, 0.0, -G, physicsClientId=client)
        floor = pybullet.createMultiBody(
            0.0, pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client), physicsClientId=client
        )
        shape = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[HALF] * 3, physicsClientId=client)
        cube = pybullet.createMultiBody(MASS, shape, physicsClientId=client)
        for body in (floor, cube):
            pybullet.changeDynamics(
                body,
                -1,
                lateralFriction=friction,
                restitution=0.0,
                linearDamping=0.0,
                angularDamping=0.0,
                physicsClientId=client,
            )
        names = inverse.BULLET_CONTACT_EXTRAS
        poses = np.zeros((tosses, frames, 1, 7))
        extras = {name: np.zeros((tosses, frames, 1, 3)) for name in names}
        for toss in range(tosses):
            orientation = rotations.uniform_random(rng, 1)[0]
            pybullet.resetBasePositionAndOrientation(
                cube, [0.0, 0.0, 0.15], rotations.wxyz_to_xyzw(orientation), physicsClientId=client
            )
            pybullet.resetBaseVelocity(cube, [1.0, -0.5, 0.0], list(rng.uniform(-5, 5, 3)), physicsClientId=client)
            for frame in range(frames):
                if frame:
                    centre = np.array(pybullet.getBasePositionAndOrientation(cube, physicsClientId=client)[0])
                    pybullet.stepSimulation(physicsClientId=client)
                    for point in pybullet.getContactPoints(cube, floor, physicsClientId=client):
                        arm = np.array(point[5]) - centre  # contact points are found before the step
                        normal_force = point[9] * np.array(point[7])
                        friction_force = point[10] * np.array(point[11]) + point[12] * np.array(point[13])
                        for name, value in zip(
                            names,
                            (normal_force, friction_force, np.cross(arm, normal_force), np.cross(arm, friction_force)),
                        ):
                            extras[name][toss, frame, 0] += value
                position, orientation_xyzw = pybullet.getBasePositionAndOrientation(cube, physicsClientId=client)
                poses[toss, frame, 0] = np.concatenate([position, rotations.xyzw_to_wxyz(np.array(orientation_xyzw))])
    finally:
        pybullet.disconnect(client)
    return cube_recordings({"train": Split(poses, np.full(tosses, frames), None, extras)})


def test_inverse_dynamics_agrees_with_pybullet_contact_forces():
    report = compare_with_bullet_contacts(bullet_cube_tosses(friction=0.6), "train")
    assert report["friction_force"]["reference_rms"] > 0.1 and report["normal_force"]["reference_rms"] > 1.0
    for name in ("contact_force", "contact_torque", "normal_force", "friction_force"):
        assert report[name]["relative_error"] < 1e-8, name
    for name in (
        "normal_torque",
        "friction_torque",
    ):  # the torque split is a model (see inverse.py), close but not exact
        assert report[name]["relative_error"] < 0.02 and report[name]["correlation"] > 0.999, name


def test_compare_with_bullet_contacts_names_missing_extras():
    with pytest.raises(KeyError, match="contact_normal_force"):
        compare_with_bullet_contacts(falling_cubes(), "train")


# ---------------------------------------------------------------- features


def coulomb_friction(mu: float):
    """Body-frame friction: mu m g against the tangential CoM velocity, applied at the CoM (a simple 'true' model)."""

    def predict(inputs: np.ndarray) -> np.ndarray:
        velocity, up = inputs[:, :3], -inputs[:, 6:9]
        tangential = velocity - np.sum(velocity * up, axis=-1, keepdims=True) * up
        speed = np.linalg.norm(tangential, axis=-1, keepdims=True)
        force = -mu * MASS * G * tangential / np.maximum(speed, 0.05)
        return np.concatenate([force, np.zeros_like(force)], axis=-1)

    return predict


def simulated_tosses(mu: float, tosses: int, frames: int, seed: int) -> Split:
    """Tosses made with the hybrid step itself and a Coulomb-like friction."""
    rng = np.random.default_rng(seed)
    scene = dynamics.single_body_scene(cube_recordings())
    orientation = rotations.uniform_random(rng, tosses)
    position = np.concatenate([rng.uniform(-0.3, 0.3, (tosses, 2)), rng.uniform(0.12, 0.2, (tosses, 1))], axis=-1)
    linear = np.concatenate([rng.uniform(-1, 1, (tosses, 2)), np.zeros((tosses, 1))], axis=-1)
    state = State(position, orientation, linear, rng.uniform(-5, 5, (tosses, 3)))
    model = HybridContactModel(coulomb_friction(mu))
    poses = [dynamics.poses_from_states(state, scene.body)]
    for _ in range(frames - 1):
        state = model.step(state, scene)
        poses.append(dynamics.poses_from_states(state, scene.body))
    return Split(np.stack(poses, axis=1)[:, :, None], np.full(tosses, frames))


def rotated_about_vertical(split: Split, angle: float, shift: np.ndarray) -> Split:
    turn = rotations.from_axis_angle(np.array([0.0, 0.0, 1.0]), angle)
    poses = split.poses.copy()
    poses[..., :3] = rotations.rotate(turn, poses[..., :3]) + shift
    poses[..., 3:] = rotations.multiply(turn, poses[..., 3:])
    return Split(poses, split.lengths)


def test_features_and_targets_are_unchanged_by_turning_the_scene_about_the_vertical(scene):
    split = simulated_tosses(mu=0.5, tosses=4, frames=40, seed=5)
    inputs, targets = training_arrays(split, scene, ContactSettings())
    turned_inputs, turned_targets = training_arrays(
        rotated_about_vertical(split, 1.1, np.array([0.4, -0.7, 0.0])), scene, ContactSettings()
    )
    assert len(inputs) > 50
    np.testing.assert_allclose(turned_inputs, inputs, atol=1e-9)
    np.testing.assert_allclose(turned_targets, targets, atol=1e-6 * np.abs(targets).max())
    assert inputs.shape[1] == features.feature_count(scene.body) == 17


def test_frictionless_tosses_give_zero_friction_and_the_forward_step_gives_them_back(scene):
    """The pipeline check behind friction = 0: our own frictionless tosses invert to no friction at all, and the
    forward step (LCP) turns the recovered impulses back into the recorded next frames."""
    split = simulated_tosses(mu=0.0, tosses=4, frames=40, seed=6)
    settings = ContactSettings()
    transitions = inverse.transitions_from_split(split, scene, settings)
    assert transitions.in_contact.sum() > 50 and np.abs(transitions.normal).max() > 0.01
    assert np.abs(transitions.friction).max() < 1e-12
    after, _ = lcp.frictionless_step(transitions.state, scene, transitions.friction, settings)
    recorded = split.poses[transitions.trajectory, transitions.frame + 1, 0]
    predicted = dynamics.poses_from_states(after, scene.body)
    np.testing.assert_allclose(predicted[:, :3], recorded[:, :3], atol=1e-12)
    assert rotations.angle_between(predicted[:, 3:], recorded[:, 3:]).max() < 1e-7


# ---------------------------------------------------------------- rollout and Lightning


def test_resting_cube_stays_at_rest_for_140_frames_under_the_hybrid_rollout():
    rest = np.array([0.2, -0.1, HALF, 1.0, 0.0, 0.0, 0.0])
    context_frames, predicted = 6, 140
    poses = np.broadcast_to(rest, (1, context_frames + predicted, 1, 7)).copy()
    recordings = cube_recordings({"test": Split(poses, np.array([context_frames + predicted]))})
    context = make_context(recordings.split("test"), DT, context_frames)
    rollout = HybridContactModel(lambda inputs: np.zeros((len(inputs), 6))).rollout(recordings, context)
    assert rollout.shape == (1, context_frames + predicted, 1, 7)
    corners = rotations.rotate(rollout[0, :, 0, None, 3:], cube_mesh(WIDTH).vertices) + rollout[0, :, 0, None, :3]
    assert -corners[..., 2].min() < 1e-3  # penetration under 1 mm
    assert np.abs(rollout[0, :, 0, :3] - rest[:3]).max() < 1e-6
    assert rotations.angle_between(rollout[0, :, 0, 3:], rest[3:]).max() < 1e-6


def test_multi_body_dataset_is_refused_at_once():
    recordings = falling_cubes(n_bodies=2)
    message = f"the hybrid model supports single-body datasets; {recordings.name} has 2 bodies"
    with pytest.raises(SingleBodyError, match=message):
        HybridModule(recordings, context_frames=6)
    with pytest.raises(SingleBodyError, match=message):
        HybridDataModule(recordings, context_frames=6)


def test_data_loaders_give_every_transition_once_in_whole_batches():
    splits = {
        name: simulated_tosses(mu=0.5, tosses=3, frames=30, seed=seed) for seed, name in enumerate(("train", "val"))
    }
    datamodule = HybridDataModule(cube_recordings(splits), context_frames=6, batch_size=16)
    datamodule.setup("fit")
    for name, loader in (("train", datamodule.train_dataloader()), ("val", datamodule.val_dataloader())):
        inputs, targets = datamodule.arrays[name]
        batches = list(loader)
        assert all(len(batch_inputs) == 16 for batch_inputs, _ in batches[:-1])
        seen_inputs = torch.cat([batch_inputs for batch_inputs, _ in batches])
        seen_targets = torch.cat([batch_targets for _, batch_targets in batches])
        order = torch.argsort(seen_inputs[:, 0] * 1e3 + seen_inputs[:, 1])
        expected = torch.argsort(inputs[:, 0] * 1e3 + inputs[:, 1])
        torch.testing.assert_close(seen_inputs[order], inputs[expected])
        torch.testing.assert_close(seen_targets[order], targets[expected])


def test_tiny_training_run_checkpoints_reloads_and_rolls_out(tmp_path):
    torch.manual_seed(0)
    splits = {
        name: simulated_tosses(mu=0.5, tosses=4, frames=30, seed=seed)
        for seed, name in enumerate(("train", "val", "test"))
    }
    recordings = cube_recordings(splits)
    datamodule = HybridDataModule(recordings, context_frames=6, batch_size=64)
    module = HybridModule(recordings, context_frames=6, hidden=(32, 16, 8))
    checkpoint = ModelCheckpoint(dirpath=tmp_path, monitor="val/pos_err", save_last=True)
    trainer = pl.Trainer(
        max_epochs=3,
        callbacks=[ValRollouts(), EarlyStopping("val/pos_err", patience=12), checkpoint],
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    trainer.fit(module, datamodule=datamodule)
    assert checkpoint.best_model_path and (tmp_path / "last.ckpt").exists()
    assert np.isfinite(float(trainer.callback_metrics["val/pos_err"]))  # the val rollout the config selects on
    statistics = datamodule.statistics
    assert float(statistics["target_std"][0]) > 0.1  # friction along the body axes is really there to learn

    best = HybridModule.load_from_checkpoint(checkpoint.best_model_path, dataset=recordings, weights_only=True)
    assert best.hparams.hidden == (32, 16, 8)
    for name, value in statistics.items():
        torch.testing.assert_close(getattr(best, name), value)
    saved = torch.load(checkpoint.best_model_path, weights_only=True)["state_dict"]
    for name, value in best.state_dict().items():
        torch.testing.assert_close(value, saved[name])

    context = make_context(recordings.split("test"), recordings.dt, 6)
    rollout = best.to_contact_model().rollout(recordings, context)
    assert rollout.shape == (4, 30, 1, 7)
    np.testing.assert_array_equal(rollout[:, :6], context.poses)
    assert np.all(np.isfinite(rollout))
