"""The paper's future-work scenes: non-convex bodies, terrain and an articulated elbow, from format to models."""

from __future__ import annotations

import copy
import dataclasses
import json

import mujoco
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from contactbench import metrics, rotations, runs
from contactbench.config import CONFIG_DIR
from contactbench.errors import NotApplicable, RecordingsError
from contactbench.generation.generator import generate_dataset
from contactbench.generation.nonconvex import SHAPES, nonconvex_shape
from contactbench.generation.scenes import SceneSpec
from contactbench.generation.terrain import RAMP_DEGREES, STEP_HEIGHT
from contactbench.ground import Ground, signed_distance
from contactbench.kinematics import hinge_child, world_vertices
from contactbench.meshes import convexity_problem
from contactbench.models.gnn.graph import MeshScene, collision_radius
from contactbench.models.gnn.module import inertia_per_mass
from contactbench.models.gnn.rigid import RigidLearnedSimulator
from contactbench.models.hybrid.dynamics import single_body_scene
from contactbench.recordings import read_recordings, write_recordings
from contactbench.sim.bullet_world import BulletSettings
from contactbench.sim.engines import engine
from contactbench.sim.mujoco_scene import ContactParameters, StateLayout, build_model
from contactbench.sim.rollout import MujocoRollouts

SIZES = {"train": 3, "val": 2, "test": 2}
SHORT = BulletSettings(frames=60)


def generated(tmp_path_factory, name: str, **scene) -> object:
    spec = SceneSpec(name=name, friction=0.3, restitution=0.125, **scene)
    folder = tmp_path_factory.mktemp(name)
    generate_dataset(spec, folder, split_sizes=SIZES, settings=SHORT, workers=1, progress=False)
    return read_recordings(folder)


@pytest.fixture(scope="module")
def ring(tmp_path_factory):
    return generated(tmp_path_factory, "nonconvex", shape="ring")


@pytest.fixture(scope="module")
def ramp(tmp_path_factory):
    return generated(tmp_path_factory, "terrain", ground="ramp")


@pytest.fixture(scope="module")
def bumps(tmp_path_factory):
    return generated(tmp_path_factory, "terrain", ground="bumps", faces=12)


@pytest.fixture(scope="module")
def elbow(tmp_path_factory):
    return generated(tmp_path_factory, "articulated", shape="elbow", bodies=2, joint_damping=0.005)


# ---------------------------------------------------------------- shapes and ground


@pytest.mark.parametrize("shape", SHAPES)
def test_nonconvex_shapes_are_watertight_unions_of_convex_pieces_in_their_principal_frame(shape):
    mesh, pieces = nonconvex_shape(shape)
    assert convexity_problem(mesh) is not None  # really concave
    assert all(convexity_problem(piece) is None for piece in pieces)
    assert sum(_volume(piece) for piece in pieces) == pytest.approx(_volume(mesh), rel=1e-9)
    com, inertia = mesh.mass_properties(0.37)
    assert np.abs(com).max() < 1e-12
    assert np.abs(inertia - np.diag(np.diag(inertia))).max() < 1e-12 * np.trace(inertia)
    assert mesh.width == pytest.approx(0.1048)


def _volume(mesh) -> float:
    v0, v1, v2 = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6)


def test_ground_distance_and_height_on_the_ramp_and_the_step(ramp, tmp_path_factory):
    ground = Ground.of(ramp)
    slope = np.tan(np.radians(RAMP_DEGREES))
    xy = np.array([[-0.5, 0.1], [0.0, -0.3], [0.7, 0.2]])
    expected = (xy[:, 0] + 1.0) * slope
    np.testing.assert_allclose(ground.height(torch.from_numpy(xy)).numpy(), expected, atol=1e-12)
    above = np.column_stack([xy, expected + 0.01])
    distance, normal = signed_distance(ground, above)
    np.testing.assert_allclose(distance, 0.01 * np.cos(np.radians(RAMP_DEGREES)), atol=1e-12)
    np.testing.assert_allclose(
        normal, np.tile([-np.sin(np.radians(RAMP_DEGREES)), 0, np.cos(np.radians(RAMP_DEGREES))], (3, 1)), atol=1e-12
    )
    step = Ground.of(generated(tmp_path_factory, "terrain", ground="step"))
    np.testing.assert_allclose(
        step.height(torch.tensor([[-0.2, 0.0], [0.2, 0.0]], dtype=torch.float64)).numpy(), [0.0, STEP_HEIGHT]
    )
    inside = signed_distance(step, np.array([[0.3, 0.0, STEP_HEIGHT - 0.004]]))[0]
    assert inside == pytest.approx(-0.004)


def test_mujoco_height_field_is_the_grounds_surface(bumps):
    """MuJoCo reads a height field's rows from +y and rescales its data: a ray down finds the ground's height."""
    params = ContactParameters.mujoco_default(1)
    model = build_model(bumps.scene, params)
    data = mujoco.MjData(model)
    data.qpos[2] = 10.0  # the body far above
    mujoco.mj_forward(model, data)
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.7, 0.7, (20, 2))
    geom = np.zeros(1, np.int32)
    hits = [
        5.0 - mujoco.mj_ray(model, data, np.array([x, y, 5.0]), np.array([0.0, 0.0, -1.0]), None, 1, -1, geom)
        for x, y in points
    ]
    expected = Ground.of(bumps).height(torch.from_numpy(points)).numpy()
    np.testing.assert_allclose(hits, expected, atol=2e-3)  # MuJoCo may split a cell along the other diagonal
    assert np.ptp(expected) > 0.01


# ---------------------------------------------------------------- the format, version 2


def test_version_two_round_trips_and_version_one_readers_keep_their_scenes(ring, ramp, elbow, tmp_path):
    for recordings in (ring, ramp, elbow):
        assert recordings.version == 2 and not recordings.flat
        again = read_recordings(write_recordings(tmp_path / recordings.name, recordings))
        assert again.meta == recordings.meta
        assert set(again.meshes) == set(recordings.meshes)
    assert len(ring.body_pieces(0)) == 12 and not ring.is_convex(0)
    assert [entry.name for entry in ramp.static] == ["ramp"]
    assert elbow.joints[0].parent == 0 and elbow.joints[0].child == 1


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: m["joints"][0].update(child="link_9"), r"joints\[0\].*'child' is 'link_9'"),
        (lambda m: m["joints"][0].update(axis=[0, 0, 0]), r"'axis'.*non-zero"),
        (lambda m: m["joints"][0].update(child="link_0"), r"'parent' and 'child' are both"),
        (lambda m: m["joints"][0].update(range=[1.0, -1.0]), r"'range'.*lowest < highest"),
        (lambda m: m.update(version=1, joints=[]) or m.update(version=3), r"field 'version' is 3"),
    ],
)
def test_bad_joints_give_one_clear_error(elbow, tmp_path, edit, message):
    folder = write_recordings(tmp_path / "elbow", elbow)
    meta = json.loads((folder / "meta.json").read_text())
    edit(meta)
    (folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(RecordingsError, match=message):
        read_recordings(folder)


def test_bad_static_geometry_and_pieces_give_one_clear_error(ramp, ring, tmp_path):
    folder = write_recordings(tmp_path / "ramp", ramp)
    meta = json.loads((folder / "meta.json").read_text())
    far = copy.deepcopy(meta)
    far["static"][0]["pose"][0] = 5000.0
    (folder / "meta.json").write_text(json.dumps(far))
    with pytest.raises(RecordingsError, match=r"static\[0\].*within 1000 m"):
        read_recordings(folder)
    (folder / "meta.json").write_text(json.dumps(meta))
    obj = (folder / "meshes" / "ramp.obj").read_text().splitlines()
    (folder / "meshes" / "ramp.obj").write_text("\n".join(line for line in obj if line != obj[-1]) + "\n")
    with pytest.raises(RecordingsError, match=r"ramp.obj.*hole.*static\[0\].mesh"):
        read_recordings(folder)
    ring_folder = write_recordings(tmp_path / "ring", ring)
    ring_meta = json.loads((ring_folder / "meta.json").read_text())
    ring_meta["bodies"][0]["pieces"][0] = ring_meta["bodies"][0]["mesh"]  # the whole ring is no convex piece
    (ring_folder / "meta.json").write_text(json.dumps(ring_meta))
    with pytest.raises(RecordingsError, match=r"pieces\[0\].*not convex"):
        read_recordings(ring_folder)


# ---------------------------------------------------------------- generated physics


def test_nothing_falls_through_the_terrain_and_bodies_come_to_rest_on_it(ramp, bumps):
    for recordings in (ramp, bumps):
        split = recordings.split("train")
        clearance = metrics.ground_clearance(split.poses, [recordings.body_mesh(0)], Ground.of(recordings))
        assert clearance.min() > -0.025  # PyBullet's one-step impacts sink as deep on the flat floor
        assert clearance[:, 0].min() > 0.03  # tosses start clear of the terrain


def test_the_hinge_keeps_its_axis_and_anchor_and_free_flight_follows_g(elbow):
    split = elbow.split("train")
    gaps, angles = metrics.joint_errors(split.poses, elbow.joints)
    assert gaps.max() < 1e-6 and angles.max() < 1e-6
    # the pair's centre of mass in its first frames (in the air) falls at g (to 1% of g: Bullet's reduced-coordinate
    # integrator does not conserve momentum exactly while the links spin about each other, 5e-4 g undamped, and
    # more while the damping changes their relative spin quickly)
    masses = np.array([body.mass for body in elbow.bodies])
    centre = np.einsum("k,ntkd->ntd", masses, split.poses[..., :3]) / masses.sum()
    acceleration = np.diff(centre[:, :4], n=2, axis=1) / elbow.dt**2
    np.testing.assert_allclose(acceleration, np.broadcast_to(elbow.gravity, acceleration.shape), atol=0.1)


def test_generation_is_deterministic(tmp_path):
    spec = SceneSpec(name="articulated", friction=0.18, restitution=0.125, shape="elbow", bodies=2)
    folders = [
        generate_dataset(spec, tmp_path / str(w), split_sizes=SIZES, settings=SHORT, workers=w, progress=False)
        for w in (1, 2)
    ]
    for name in ("meta.json", "train.npz", "val.npz", "meshes/link.obj"):
        assert (folders[0] / name).read_bytes() == (folders[1] / name).read_bytes()


# ---------------------------------------------------------------- models


def test_mujoco_simulates_the_elbow_as_a_hinge_from_recorded_states(elbow):
    rollouts = MujocoRollouts(elbow.scene, 1)
    split = elbow.split("val")
    qpos, qvel = rollouts.layout.pack(split.poses[:, 0], split.velocities[:, 0])
    poses, free_qvel = rollouts.layout.unpack(qpos, qvel)
    np.testing.assert_allclose(poses, split.poses[:, 0], atol=1e-12)
    result = rollouts.simulate(ContactParameters.mujoco_default(2), split.poses[:, 0], split.velocities[:, 0], 30)
    gaps, angles = metrics.joint_errors(result.poses[0], elbow.joints)
    assert gaps.max() < 1e-9 and angles.max() < 1e-9 and not result.unstable.any()
    # the first frames are in the air: MuJoCo and PyBullet agree there to a fraction of a millimetre (MuJoCo damps
    # the hinge implicitly, PyBullet explicitly, and their multibody integrators differ)
    np.testing.assert_allclose(result.poses[0][:, :2, :, :3], split.poses[:, 1:3, :, :3], atol=3e-4)


def test_the_pybullet_engine_replays_generated_pieces_and_terrain(ring, ramp):
    """The engine's world of a version-2 scene is the generator's: the generating parameters reproduce the tosses (the
    bumps are left out: their tosses are chaotic at triangle edges, and the recorded first frame, read back from
    PyBullet, differs from the sampled one in the last bit)."""
    for recordings, friction in ((ring, 0.3), (ramp, 0.3)):
        rollouts = engine("bullet").rollouts(recordings.scene, 1)
        split = recordings.split("val")
        parameters = engine("bullet").default_parameters(1)
        parameters = dataclasses.replace(parameters, object_friction=(friction,), restitution=(0.125,))
        try:
            result = rollouts.simulate(parameters, split.poses[:, 0], split.velocities[:, 0], split.n_frames - 1)
        finally:
            rollouts.close()
        np.testing.assert_allclose(result.poses[0][..., :3], split.poses[:, 1:, :, :3], atol=1e-9)


def test_state_layout_of_free_bodies_is_the_plain_one(ring):
    model = build_model(ring.scene, ContactParameters.mujoco_default(1))
    assert StateLayout.of(ring.scene, model).free and model.ngeom == 1 + 12


def elbow_simulator(elbow, **options) -> RigidLearnedSimulator:
    """A tiny rigid GNN of the elbow scene, its hinge and masses as recorded."""
    scene = MeshScene.of(elbow)
    return RigidLearnedSimulator(
        scene,
        elbow.dt,
        elbow.floor_z,
        elbow.gravity,
        collision_radius(scene.widths),
        0.25 * scene.widths.max(),
        joints=tuple(elbow.joints),
        masses=np.array([body.mass for body in elbow.bodies]),
        latent_size=8,
        message_passing_steps=1,
        **options,
    )


def test_the_gnn_closes_a_hinge_exactly_and_reads_the_terrain(elbow, ramp):
    simulator = elbow_simulator(elbow)
    poses = torch.as_tensor(elbow.split("train").poses[:, 5].copy())
    broken = poses.clone()
    broken[:, 1, :3] += 0.01
    broken[:, 1, 3:] = torch.as_tensor(
        rotations.multiply(rotations.from_axis_angle([1.0, 0, 0], 0.1), broken[:, 1, 3:].numpy())
    )
    kept = simulator.bodies.keep_joints(broken).numpy()
    gaps, angles = metrics.joint_errors(kept, elbow.joints)
    assert gaps.max() < 1e-12 and angles.max() < 1e-12
    centre = lambda p: p[:, :, :3].mean(axis=1)  # noqa: E731 (equal masses)
    np.testing.assert_allclose(centre(kept), centre(broken.numpy()), atol=1e-12)
    ramp_scene = MeshScene.of(ramp)
    terrain = RigidLearnedSimulator(
        ramp_scene,
        ramp.dt,
        ramp.floor_z,
        ramp.gravity,
        collision_radius(ramp_scene.widths),
        0.025,
        ground=Ground.of(ramp),
        latent_size=8,
        message_passing_steps=1,
    )
    on_ramp = torch.tensor([[[0.0, 0.0, 0.18 + 0.02]]], dtype=torch.float64)
    assert terrain.clearance(on_ramp).item() == pytest.approx((0.2 - np.tan(np.radians(10))) * np.cos(np.radians(10)))
    assert terrain.ground_normal_features == 3


def test_the_rigid_gnn_swings_the_elbow_as_pybullet_does_with_its_joint_reaction_and_damping(elbow):
    """With the network silent (no contact), the rigid GNN's integrator is Newton-Euler with the hinge's reaction and
    the recorded damping: it follows the generator's multibody in the air to a few micrometres, keeps the hinge
    before any projection, and the pair's centre of mass falls at g. Leaving the damping out misses by far more."""
    simulator = elbow_simulator(elbow, solid_inertia=inertia_per_mass(elbow, MeshScene.of(elbow)))
    for parameter in simulator.network.parameters():
        torch.nn.init.zeros_(parameter)
    poses = torch.as_tensor(np.concatenate([elbow.split(name).poses for name in ("train", "val", "test")]))
    history, steps = simulator.velocity_history + 1, 4
    meshes = [elbow.body_mesh(k) for k in range(2)]
    clearance = metrics.ground_clearance(poses[:, : history + steps].numpy(), meshes, Ground.of(elbow))
    in_the_air = clearance.min(axis=(1, 2)) > 0.002
    assert in_the_air.sum() >= 4
    poses = poses[in_the_air]
    frames = poses[:, :history]
    for _ in range(steps):  # integrated without keep_joints: the hinge is the reaction's alone
        window = frames[:, -history:]
        frames = torch.cat(
            [frames, simulator.bodies.integrate(window, *simulator.accelerations(window))[:, None]], dim=1
        )
    predicted, recorded = frames[:, history:].detach().numpy(), poses[:, history : history + steps].numpy()
    error = np.abs(predicted[..., :3] - recorded[..., :3]).max()
    assert error < 5e-5
    gaps, angles = metrics.joint_errors(predicted, elbow.joints)
    assert gaps.max() < 1e-5 and angles.max() < 1e-9
    masses = np.array([body.mass for body in elbow.bodies])
    centre = np.einsum("k,ntkd->ntd", masses, frames[:, history - 2 :, :, :3].detach().numpy()) / masses.sum()
    falling = np.diff(centre, n=2, axis=1) / elbow.dt**2
    np.testing.assert_allclose(falling, np.broadcast_to(elbow.gravity, falling.shape), atol=1e-8)
    simulator.bodies.joints = (dataclasses.replace(elbow.joints[0], damping=0.0),)
    window = poses[:, :history]
    undamped = simulator.bodies.integrate(window, *simulator.accelerations(window)).detach().numpy()
    assert (
        np.abs(undamped[..., :3] - recorded[:, 0, :, :3]).max() > 10 * np.abs(predicted - recorded)[:, 0, :, :3].max()
    )


def test_models_that_know_only_the_flat_floor_refuse_the_new_scenes_in_one_line(ramp, elbow):
    with pytest.raises(NotApplicable, match="flat floor"):
        engine("drake").check_scene(ramp.scene)
    engine("bullet").check_scene(elbow.scene)  # PyBullet and Drake build hinges (test_bullet_engine.py, test_drake.py)
    with pytest.raises(NotApplicable, match="terrain"):
        single_body_scene(ramp.scene)
    from contactbench.models.residual.correction import Bodies

    for recordings in (ramp, elbow):
        with pytest.raises(NotApplicable, match="terrain or joints"):
            Bodies.of(recordings.scene)


def test_metrics_score_joints_and_the_true_ground(elbow, ramp):
    split = elbow.split("val")
    exact = metrics.compute_metrics(
        split.poses, split.poses, split.lengths, 1, [elbow.body_mesh(0)] * 2, 0.0, joints=elbow.joints
    )
    assert exact.summary["joint_gap_m"] < 1e-12
    child, _ = hinge_child(split.poses[..., 0, :], split.velocities[..., 0, :], elbow.joints[0], 0.0, 0.0)
    moved = split.poses.copy()
    moved[..., 1, :3] = child[..., :3] + [0.0, 0.0, 0.003]
    moved[..., 1, 3:] = child[..., 3:]
    off = metrics.compute_metrics(
        split.poses, moved, split.lengths, 1, [elbow.body_mesh(0)] * 2, 0.0, joints=elbow.joints
    )
    assert off.summary["joint_gap_m"] == pytest.approx(0.003)
    ramp_split = ramp.split("val")
    sunk = ramp_split.poses.copy()
    sunk[..., 2] -= 0.5  # half a metre down: inside the ramp wherever it is
    lowest = world_vertices(sunk[..., 0, :], ramp.body_mesh(0).vertices)
    ground = Ground.of(ramp)
    result = metrics.compute_metrics(
        ramp_split.poses, sunk, ramp_split.lengths, 1, [ramp.body_mesh(0)], 0.0, ground=ground
    )
    expected = -signed_distance(ground, lowest)[0].min(axis=-1)
    assert result.summary["floor_penetration_m"] == pytest.approx(expected[:, 1:].mean(), rel=1e-9)


# ---------------------------------------------------------------- the pipeline


@pytest.mark.slow
def test_train_runs_every_model_on_the_new_families_or_skips_it_in_one_line(tmp_path):
    """train.py at budget=smoke on the elbow: the GNN fits and scores it (joint errors in metrics.json); the models
    that know only free bodies on the flat floor refuse it (NotApplicable: one line, the job skipped)."""
    overrides = [
        "variant=articulated_0.005",
        "budget=smoke",
        "test=true",
        "generation.split_sizes={train:6,val:4,test:4}",
        f"paths.log_dir={tmp_path}/outputs",
        f"paths.data_dir={tmp_path}/data",
    ]

    def config(model: str):
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            return compose(config_name="train", overrides=[*overrides, f"model={model}"])

    runs.train(config("gnn"), tmp_path / "gnn")
    scored = json.loads((tmp_path / "gnn" / "test" / "metrics.json").read_text())
    assert scored["joint_gap_m"] < 1e-9 and scored["joint_axis_error_rad"] < 1e-9  # the GNN keeps the hinge
    assert np.isfinite(scored["pos_err"])
    for model in ("hybrid", "residual", "gnn_paper"):
        with pytest.raises(NotApplicable):
            runs.train(config(model), tmp_path / model)
