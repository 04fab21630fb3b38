"""The real elbow (dair_pll's 541 tosses): the converter, the shipped dataset's physics, and bad input."""

from __future__ import annotations

import copy
import hashlib
import json
import zipfile

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from contactbench import contactnets_elbow, kinematics, metrics, rotations, runs
from contactbench.config import CONFIG_DIR
from contactbench.errors import ContactbenchError, NotApplicable, RecordingsError
from contactbench.recordings import read_recordings, write_recordings

SHIPPED = CONFIG_DIR.parent / "assets" / "contactnets_elbow"


@pytest.fixture(scope="module")
def shipped():
    return read_recordings(SHIPPED)


def _published_file(path, rows: np.ndarray, header: bytes = contactnets_elbow.TENSOR_HEADER) -> None:
    """A torch archive laid out as the publisher's are: the pickled header and the raw float64 storage."""
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", header)
        archive.writestr("archive/data/0", np.ascontiguousarray(rows, dtype="<f8").tobytes())
        archive.writestr("archive/version", "3\n")


def _free_flight_rows(rng: np.random.Generator) -> np.ndarray:
    """Drake state rows of an elbow tossed without spin and a still hinge, high above the floor (exact ballistics)."""
    t = np.arange(contactnets_elbow.FRAMES) * contactnets_elbow.DT
    rows = np.zeros((contactnets_elbow.FRAMES, contactnets_elbow.COLUMNS))
    rows[:, 0] = 1.0
    velocity = rng.uniform(-1, 1, 3)
    rows[:, 4:7] = np.array([0.0, 0.0, 5.0]) + velocity * t[:, None] + 0.5 * np.array([0, 0, -9.81]) * t[:, None] ** 2
    rows[:, 7] = rng.uniform(-np.pi, np.pi)
    rows[:, 11:14] = velocity + np.array([0, 0, -9.81]) * t[:, None]
    return rows


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A dair_pll checkout in miniature: LICENSE at its root, the 541 files under assets/contactnets_elbow."""
    root = tmp_path_factory.mktemp("dair_pll")
    folder = root / "assets" / "contactnets_elbow"
    folder.mkdir(parents=True)
    (root / "LICENSE").write_text("BSD 3-Clause License\n")
    rng = np.random.default_rng(0)
    for i in range(contactnets_elbow.N_TOSSES):
        _published_file(folder / f"{i}.pt", _free_flight_rows(rng))
    return folder


def _digest(folder) -> dict[str, str]:
    return {path.name: hashlib.sha256(path.read_bytes()).hexdigest() for path in sorted(folder.rglob("*.*"))}


def test_the_converter_writes_the_same_bytes_every_run_with_the_licence_and_a_50_30_20_split(source, tmp_path):
    first = contactnets_elbow.convert(source, tmp_path / "a")
    second = contactnets_elbow.convert(source, tmp_path / "b")
    assert _digest(first) == _digest(second)
    assert (first / "LICENSE").read_text() == "BSD 3-Clause License\n"
    dataset = read_recordings(first)
    sizes = {name: split.n_trajectories for name, split in dataset.splits.items()}
    assert sizes == {"train": 270, "val": 162, "test": 109}
    indices = np.concatenate([split.extras["source_index"] for split in dataset.splits.values()])
    assert sorted(indices.tolist()) == list(range(contactnets_elbow.N_TOSSES))
    # the hinge is kept exactly, and a still hinge in free flight leaves both bars on the same parabola
    split = dataset.split("train")
    gap, tilt = metrics.joint_errors(split.poses, dataset.joints)
    assert gap.max() < 1e-12 and tilt.max() < 1e-6
    np.testing.assert_allclose(split.velocities[:, :, 1, :3], split.velocities[:, :, 0, :3], atol=1e-12)


def test_the_converter_refuses_a_file_it_would_have_to_unpickle_in_one_line(source, tmp_path):
    folder = tmp_path / "assets" / "contactnets_elbow"
    folder.mkdir(parents=True)
    for path in source.iterdir():
        (folder / path.name).write_bytes(path.read_bytes())
    (tmp_path / "LICENSE").write_text("licence")
    header = contactnets_elbow.TENSOR_HEADER.replace(b"_rebuild_tensor_v2", b"os.system\nq\x00(X\x02\x00\x00\x00id")
    _published_file(folder / "7.pt", np.zeros((121, 15)), header=header)
    with pytest.raises(ContactbenchError, match=r"7\.pt: field 'data\.pkl' is not the published header"):
        contactnets_elbow.convert(folder, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    (folder / "7.pt").unlink()
    with pytest.raises(ContactbenchError, match=r"1 of the 541 files are missing, first 7\.pt"):
        contactnets_elbow.convert(folder, tmp_path / "out")
    assert contactnets_elbow.main([str(folder), str(tmp_path / "out")]) == 1
    assert not (tmp_path / "out").exists()


def test_the_shipped_elbow_keeps_its_hinge_and_its_split(shipped):
    assert shipped.real and len(shipped.joints) == 1 and shipped.n_bodies == 2
    sizes = {name: split.n_trajectories for name, split in shipped.splits.items()}
    assert sizes == {"train": 270, "val": 162, "test": 109}
    for split in shipped.splits.values():
        gap, tilt = metrics.joint_errors(split.poses, shipped.joints)
        assert gap.max() < 1e-9 and tilt.max() < 1e-6
    # the bars' inertia is a 10 x 5 x 5 cm uniform solid's, not the URDF's cube value
    _, inertia = shipped.inertial(0)
    np.testing.assert_allclose(np.diag(inertia), [1.5417e-4, 3.8542e-4, 3.8542e-4], rtol=1e-3)


def test_the_shipped_elbow_falls_with_gravity_in_free_flight(shipped):
    """The two bars' centre of mass on each toss's first stretch clear of the floor: a parabola in time whose curvature
    is g within the tracker's own error (the real cube's free flight, read the same way, gives 9.60), and no
    horizontal acceleration."""
    split = shipped.split("train")
    meshes = [shipped.body_mesh(k) for k in range(2)]
    clear = np.min(
        [kinematics.world_vertices(split.poses[..., k, :], meshes[k].vertices)[..., 2].min(-1) for k in range(2)],
        axis=0,
    )
    centre = split.poses[..., :3].mean(axis=-2)
    accelerations = []
    for n in range(split.n_trajectories):
        flight = int(np.argmax(clear[n] < 0.01)) if (clear[n] < 0.01).any() else split.n_frames
        if flight >= 15:
            time = np.arange(flight) * shipped.dt
            accelerations.append([2 * np.polyfit(time, centre[n, :flight, axis], 2)[0] for axis in range(3)])
    accelerations = np.array(accelerations)
    assert len(accelerations) > 100
    vertical = np.median(accelerations[:, 2])
    assert -9.81 * 1.04 < vertical < -9.81 * 0.96
    assert np.abs(np.median(accelerations[:, :2], axis=0)).max() < 0.3


def test_a_recording_whose_hinge_anchors_part_is_refused_naming_the_file_and_the_field(shipped, tmp_path):
    folder = write_recordings(tmp_path / "elbow", shipped.for_models(["train", "val", "test"]))
    meta = json.loads((folder / "meta.json").read_text())
    moved = copy.deepcopy(meta)
    moved["joints"][0]["parent_anchor"] = [-0.035, 0.09, 0.0]  # 3 cm off
    (folder / "meta.json").write_text(json.dumps(moved))
    with pytest.raises(RecordingsError, match=r"train\.npz: field 'poses': trajectory 0, frame 0: hinge joints\[0\]"):
        read_recordings(folder)
    (folder / "meta.json").write_text(json.dumps(meta))
    twisted = copy.deepcopy(shipped)
    twisted.splits["val"].poses[3, 10, 1, 3:] = rotations.multiply(
        twisted.splits["val"].poses[3, 10, 1, 3:], rotations.from_axis_angle(np.array([1.0, 0, 0]), 0.3)
    )
    with pytest.raises(RecordingsError, match=r"val\.npz \(being written\): field 'poses': trajectory 3, frame 10"):
        write_recordings(tmp_path / "twisted", twisted)
    assert not (tmp_path / "twisted").exists()


@pytest.mark.slow
def test_every_model_runs_on_the_elbow_at_smoke_or_refuses_it_in_one_line(shipped, tmp_path):
    """train.py at budget=smoke on a few of the real elbow's tosses, loaded as a user's folder: every engine, untuned
    and identified with its hinge, and the GNN fit and score it, keeping the hinge; the hybrid and the paper's GNN
    refuse in one line (sysid_mjx: tests/test_sysid_mjx.py, which shares its compiled functions)."""
    few = shipped.for_models(["train", "val", "test"])
    few.splits = {name: split.select(range(4)) for name, split in few.splits.items()}
    folder = write_recordings(tmp_path / "elbow", few)
    overrides = [
        "dataset=recordings",
        f"recordings={folder}",
        "budget=smoke",
        "test=true",
        f"paths.log_dir={tmp_path}/outputs",
    ]

    def config(model: str):
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            return compose(config_name="train", overrides=[*overrides, f"model={model}"])

    for model in ("mujoco_default", "bullet_default", "drake_default", "sysid", "sysid_bullet", "sysid_drake", "gnn"):
        runs.train(config(model), tmp_path / model)
        scored = json.loads((tmp_path / model / "test" / "metrics.json").read_text())
        assert np.isfinite(scored["pos_err"]) and np.isfinite(scored["rot_err_rad"]), model
        assert scored["joint_gap_m"] < 1e-6, model  # every model keeps the hinge
        if model.startswith("sysid"):
            fitted = json.loads((tmp_path / model / "fitted.json").read_text())
            assert {"joint_damping_0", "joint_friction_0", "inertia_scale"} <= set(fitted["parameters"]), model
    for model in ("hybrid", "gnn_paper"):
        with pytest.raises(NotApplicable):
            runs.train(config(model), tmp_path / model)
