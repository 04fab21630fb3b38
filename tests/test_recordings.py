"""The recordings reader/writer: round trip, the shipped real data, and a clear error for every malformed input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import falling_cubes

from contactbench.config import REPO_ROOT
from contactbench.errors import RecordingsError
from contactbench.recordings import read_recordings, write_recordings

REAL_CUBE = REPO_ROOT / "assets" / "contactnets_cube"


def test_round_trip_is_identical(tmp_path, small_recordings):
    write_recordings(tmp_path / "ds", small_recordings)
    again = read_recordings(tmp_path / "ds")
    assert again.meta == small_recordings.meta  # unknown keys preserved
    for name, split in small_recordings.splits.items():
        np.testing.assert_array_equal(again.splits[name].poses, split.poses)
        np.testing.assert_array_equal(again.splits[name].velocities, split.velocities)
        np.testing.assert_array_equal(again.splits[name].lengths, split.lengths)
        np.testing.assert_array_equal(again.splits[name].extras["source_index"], split.extras["source_index"])
    np.testing.assert_array_equal(again.body_mesh(0).vertices, small_recordings.body_mesh(0).vertices)
    np.testing.assert_array_equal(again.body_mesh(0).faces, small_recordings.body_mesh(0).faces)


def test_writes_are_byte_deterministic_and_leave_no_temporaries(tmp_path, small_recordings):
    write_recordings(tmp_path / "a", small_recordings)
    write_recordings(tmp_path / "b", small_recordings)
    write_recordings(tmp_path / "b", small_recordings)  # rewriting in place swaps the folder atomically
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert files_a == files_b
    for relative in files_a:
        assert (tmp_path / "a" / relative).read_bytes() == (tmp_path / "b" / relative).read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


def test_invalid_data_is_never_written(tmp_path, small_recordings):
    small_recordings.splits["train"].poses[0, 1, 0, 3] = 5.0
    with pytest.raises(RecordingsError, match="being written"):
        write_recordings(tmp_path / "ds", small_recordings)
    assert not (tmp_path / "ds").exists()
    assert list(tmp_path.iterdir()) == []


def test_real_cube_asset_validates():
    dataset = read_recordings(REAL_CUBE)
    assert dataset.real
    assert {name: split.n_trajectories for name, split in dataset.splits.items()} == {
        "train": 275,
        "val": 165,
        "test": 110,
    }
    assert dataset.widths() == pytest.approx([0.1048])
    lengths = np.concatenate([split.lengths for split in dataset.splits.values()])
    assert lengths.min() >= 85 and lengths.max() <= 139
    assert (REAL_CUBE / "LICENSE").is_file()


def test_lengths_mask_trailing_nan(tmp_path):
    dataset = falling_cubes(n_trajectories=2, n_frames=8)
    split = dataset.splits["train"]
    split.lengths[1] = 5
    split.poses[1, 5:] = np.nan
    split.velocities[1, 5:] = np.nan
    write_recordings(tmp_path / "ds", dataset)
    assert read_recordings(tmp_path / "ds").splits["train"].valid_mask().sum() == 8 + 5


# ---------------------------------------------------------------- malformed datasets


def _write(tmp_path: Path) -> Path:
    root = tmp_path / "ds"
    write_recordings(root, falling_cubes(n_trajectories=2, n_frames=6, n_bodies=2))
    return root


def _edit_meta(root: Path, edit) -> None:
    meta = json.loads((root / "meta.json").read_text())
    edit(meta)
    (root / "meta.json").write_text(json.dumps(meta))


def _edit_split(root: Path, edit, split: str = "train") -> None:
    with np.load(root / f"{split}.npz", allow_pickle=False) as archive:
        arrays = {name: archive[name] for name in archive.files}
    edit(arrays)
    np.savez(root / f"{split}.npz", **arrays)


def _remove(root: Path, relative: str) -> None:
    (root / relative).unlink()


def _set_nan(arrays):
    arrays["poses"][1, 3, 1, 0] = np.nan


def _scale_quaternion(arrays):
    arrays["poses"][0, 2, 1, 3:] *= 1.01


def _break_mesh(root: Path) -> None:
    lines = (root / "meshes" / "cube.obj").read_text().splitlines()
    (root / "meshes" / "cube.obj").write_text("\n".join(lines[:-1]) + "\n")  # drop one face: a hole


MALFORMED = {
    "missing meta.json": (lambda r: _remove(r, "meta.json"), "meta.json: missing"),
    "missing split file": (lambda r: _remove(r, "val.npz"), r"val.npz: split file missing"),
    "wrong format": (lambda r: _edit_meta(r, lambda m: m.update(format="other")), "field 'format'"),
    "wrong version": (lambda r: _edit_meta(r, lambda m: m.update(version=3)), "field .version. is 3"),
    "mesh missing": (
        lambda r: _remove(r, "meshes/cube.obj"),
        r"cube.obj: mesh file missing \(meta.json bodies\[0\].mesh\)",
    ),
    "mesh not closed": (_break_mesh, "not a closed triangle mesh: an edge has only one face"),
    "shape vs bodies": (
        lambda r: _edit_meta(r, lambda m: m["bodies"].pop()),
        r"train.npz: field 'poses' has shape \(2, 6, 2, 7\) \(expected \[N, T, K=1, 7\]",
    ),
    "non-unit quaternion": (
        lambda r: _edit_split(r, _scale_quaternion),
        "trajectory 0, frame 2, body 1: quaternion norm",
    ),
    "NaN in valid frames": (lambda r: _edit_split(r, _set_nan), "field 'poses': trajectory 1, frame 3, body 1: NaN"),
    "lengths out of range": (
        lambda r: _edit_split(r, lambda a: a.update(lengths=np.array([6, 9]))),
        "field 'lengths': trajectory 1 has length 9 \\(expected 1..6\\)",
    ),
    "non-positive dt": (lambda r: _edit_meta(r, lambda m: m.update(dt=0.0)), "field 'dt' is 0.0"),
    "non-positive mass": (
        lambda r: _edit_meta(r, lambda m: m["bodies"][1].update(mass=-1)),
        r"bodies\[1\]: field 'mass' is -1",
    ),
    "velocities shape": (
        lambda r: _edit_split(r, lambda a: a.update(velocities=a["velocities"][..., :3])),
        "field 'velocities' has shape",
    ),
    "pickled object array": (
        lambda r: _edit_split(r, lambda a: a.update(poses=np.array([{"a": 1}], dtype=object))),
        "without unpickling|dtype object",
    ),
    "invalid json": (lambda r: (r / "meta.json").write_text("{not json"), "meta.json: not valid JSON"),
    "gravity not a vector": (lambda r: _edit_meta(r, lambda m: m.update(gravity=[0, -9.8])), "field 'gravity'"),
    "split not in meta": (lambda r: _edit_meta(r, lambda m: m["splits"].pop("test")), "no split 'test'"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_dataset_gives_one_clear_error(tmp_path, case):
    corrupt, expected = MALFORMED[case]
    root = _write(tmp_path)
    corrupt(root)
    splits = ["train", "val", "test"] if case != "split not in meta" else ["test"]
    with pytest.raises(RecordingsError, match=expected) as caught:
        read_recordings(root, splits)
    assert str(root) in str(caught.value)  # the message names the file


def test_copy_of_real_data_in_a_new_place_reads(tmp_path):
    shutil.copytree(REAL_CUBE, tmp_path / "cube")
    dataset = read_recordings(tmp_path / "cube", ["val"])
    assert list(dataset.splits) == ["val"]


def test_writer_refuses_what_the_reader_would_reject(tmp_path, small_recordings):
    small_recordings.splits["train"].lengths = small_recordings.splits["train"].lengths.astype(float)
    with pytest.raises(RecordingsError, match="'lengths' has dtype float64"):
        write_recordings(tmp_path / "a", small_recordings)
    no_mesh = falling_cubes()
    no_mesh.meshes.clear()
    with pytest.raises(RecordingsError, match="no mesh given for 'meshes/cube.obj'"):
        write_recordings(tmp_path / "b", no_mesh)


def test_select_trims_per_frame_extras_with_the_poses():
    dataset = falling_cubes(n_trajectories=3, n_frames=8)
    split = dataset.splits["train"]
    split.extras["contact_normal_force"] = np.zeros((3, 8, 1, 3))
    split.lengths[:] = [8, 5, 4]
    chosen = split.select([1, 2])
    assert chosen.poses.shape[:2] == (2, 5) and chosen.extras["contact_normal_force"].shape == (2, 5, 1, 3)
    assert chosen.extras["source_index"].tolist() == [1, 2]
