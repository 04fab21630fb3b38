"""Hostile and careless input: crafted checkpoints, other runs' folders, paths and bytes in datasets.

One clear error, nothing changed."""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import falling_cubes
from hypothesis import HealthCheck, given
from hypothesis import settings as hypothesis_settings
from hypothesis import strategies as st
from test_pipeline import compose_config, run_entry_point

from contactbench import checks, cli, runs
from contactbench.errors import ContactbenchError, RecordingsError
from contactbench.models.sysid.module import NevergradSearch, check_search_state
from contactbench.recordings import read_recordings, write_recordings

SYSID = ["model=sysid", "dataset=contactnets_cube", "budget=smoke"]
EXTERNAL_CONF = Path(__file__).parent / "external_model" / "conf"  # a model of one's own (docs/ADDING_A_MODEL.md)


class _CreatesFile:
    """A pickle payload: unpickling it creates (truncates) the file at `path`."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def tree_digest(root: Path) -> dict[str, str]:
    """Every file and folder below root, hidden ones included: its bytes' hash (folders: 'dir')."""
    digest = {}
    for path in sorted(Path(root).rglob("*")):
        relative = str(path.relative_to(root))
        digest[relative] = "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return digest


def assert_refused(result, *needles: str) -> str:
    """Exit status 2, exactly one stderr line starting 'error:' that contains every needle, no traceback."""
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, result.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr[-3000:]
    assert "Traceback" not in result.stdout + result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def finished_sysid_run(tmp_path_factory) -> Path:
    """A finished train.py run of SysID on budget=smoke, as a user would have it (with .hydra/, train.log, csv/)."""
    tmp_path = tmp_path_factory.mktemp("finished")
    run_dir = tmp_path / "run"
    result = run_entry_point("train.py", [*SYSID, f"hydra.run.dir={run_dir}"], tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert (run_dir / ".hydra" / "config.yaml").is_file() and (run_dir / "signature.json").is_file()
    console = result.stdout + result.stderr
    assert "💡" not in console and "litlogger" not in console, console  # Lightning's advert (cli.quiet_third_party)
    return run_dir


def _copy_run(run_dir: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    return copy


# ---------------------------------------------------------------- a refused run leaves its folder as it was


@pytest.mark.parametrize(
    "script, overrides, needle",
    [
        ("train.py", ["model=hybrid", "dataset=contactnets_cube", "budget=smoke"], "other settings"),
        ("train.py", ["model=mujoco_default", "dataset=contactnets_cube", "budget=smoke"], "other settings"),
        ("train.py", [*SYSID, "model.module.position_exponent=1"], "other settings"),
        ("train.py", [*SYSID, "context_frames=8"], "other settings"),
        ("evaluate.py", [*SYSID, "split=val"], "holds a train run; evaluate would write into it"),
        ("generate.py", ["dataset=contactnets_cube"], "holds a train run; generate would write into it"),
    ],
)
def test_a_refused_command_changes_no_byte_of_the_folder(finished_sysid_run, tmp_path, script, overrides, needle):
    run_dir = _copy_run(finished_sysid_run, tmp_path)
    before = tree_digest(run_dir)
    result = run_entry_point(script, [*overrides, f"hydra.run.dir={run_dir}"], tmp_path, timeout=300)
    assert_refused(result, str(run_dir / "signature.json"), needle)
    assert tree_digest(run_dir) == before


def test_a_refused_multirun_job_changes_no_byte_of_the_folder(finished_sysid_run, tmp_path):
    sweep = tmp_path / "sweep"
    job = (
        sweep / "budget=smoke,dataset=contactnets_cube,model=hybrid"
    )  # this job's folder: another run was copied there
    shutil.copytree(finished_sysid_run, job)
    before = tree_digest(job)
    overrides = ["-m", "model=hybrid", "dataset=contactnets_cube", "budget=smoke", f"hydra.sweep.dir={sweep}"]
    result = run_entry_point("train.py", overrides, tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]  # a sweep goes on past a skipped job
    assert "other settings" in result.stderr and "(job skipped)" in result.stderr
    assert tree_digest(job) == before


def test_resuming_a_finished_run_with_the_same_settings_is_accepted(finished_sysid_run, tmp_path):
    run_dir = _copy_run(finished_sysid_run, tmp_path)
    result = run_entry_point("train.py", [*SYSID, f"hydra.run.dir={run_dir}"], tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((run_dir / "fitted.json").read_text()) == json.loads(
        (finished_sysid_run / "fitted.json").read_text()
    )


# ---------------------------------------------------------------- resuming never executes anything


def _craft_checkpoint(run_dir: Path, edit) -> Path:
    path = run_dir / "checkpoints" / "last.ckpt"
    checkpoint = torch.load(path, weights_only=True)
    edit(checkpoint)
    torch.save(checkpoint, path)
    return path


def test_a_checkpoint_with_pickled_optimiser_bytes_is_refused_and_nothing_runs(finished_sysid_run, tmp_path):
    run_dir = _copy_run(finished_sysid_run, tmp_path)
    marker = tmp_path / "payload-ran"
    payload = pickle.dumps(_CreatesFile(marker))
    assert not marker.exists()

    def add_optimiser_bytes(checkpoint):  # as an older contactbench stored it, with a payload instead of an optimiser
        state = checkpoint["callbacks"]["NevergradSearch"]
        state.update(optimizer=torch.frombuffer(bytearray(payload), dtype=torch.uint8), restart=1, generation=0)
        state["results"] = state["results"][:1]

    checkpoint = _craft_checkpoint(run_dir, add_optimiser_bytes)
    before = tree_digest(run_dir)
    result = run_entry_point("train.py", [*SYSID, f"hydra.run.dir={run_dir}"], tmp_path, timeout=300)
    assert_refused(result, str(checkpoint), "callbacks.NevergradSearch", "field 'optimizer'", "unpickling")
    assert not marker.exists()
    assert tree_digest(run_dir) == before


def test_a_checkpoint_that_is_itself_a_pickle_payload_is_refused_and_nothing_runs(finished_sysid_run, tmp_path):
    run_dir = _copy_run(finished_sysid_run, tmp_path)
    marker = tmp_path / "payload-ran"
    checkpoint = run_dir / "checkpoints" / "last.ckpt"
    checkpoint.write_bytes(pickle.dumps({"callbacks": _CreatesFile(marker)}, protocol=2))
    before = tree_digest(run_dir)
    result = run_entry_point("train.py", [*SYSID, f"hydra.run.dir={run_dir}"], tmp_path, timeout=300)
    assert_refused(result, str(checkpoint), "not a checkpoint contactbench can resume", "resume=false")
    assert not marker.exists()
    assert tree_digest(run_dir) == before


def _valid_state() -> dict:
    return {
        "restart": 1,
        "generation": 2,
        "evaluations": 24,
        "unstable": 0,
        "results": [{"vector": [0.3, 0.2, 2000.0, 60.0], "val_loss": 0.5}],
        "asked": torch.zeros((8, 4), dtype=torch.float64),
        "losses": torch.ones(8, dtype=torch.float64),
    }


BAD_STATES = {
    "pickled optimiser": (
        lambda s: s.update(optimizer=torch.frombuffer(bytearray(b"\x80\x02cos\nsystem\n"), dtype=torch.uint8)),
        "'optimizer'",
    ),
    "unknown field": (lambda s: s.update(extra=1), "field 'extra' is not part of the search state"),
    "missing field": (lambda s: s.pop("losses"), "field 'losses' is missing"),
    "negative counter": (
        lambda s: s.update(generation=-1),
        "field 'generation' is -1 (expected a non-negative integer)",
    ),
    "float counter": (lambda s: s.update(restart=1.0), "field 'restart' is 1.0"),
    "results vs restarts": (lambda s: s.update(restart=3), "field 'results'"),
    "malformed result": (lambda s: s["results"][0].update(vector="rm -rf"), "field 'results[0]' is malformed"),
    "asked as bytes": (
        lambda s: s.update(asked=torch.zeros(8, dtype=torch.uint8)),
        "field 'asked' is a torch.uint8 tensor",
    ),
    "losses length": (lambda s: s.update(losses=torch.ones(7, dtype=torch.float64)), "field 'losses'"),
    "non-finite history": (lambda s: s["asked"].fill_(float("nan")), "field 'asked' holds NaN"),
    "not a dict": (lambda s: s.clear(), "field 'restart' is missing"),
}


@pytest.mark.parametrize("case", sorted(BAD_STATES))
def test_a_malformed_search_state_is_refused_by_field(case):
    edit, expected = BAD_STATES[case]
    state = _valid_state()
    check_search_state(state, "x")  # the unedited state is valid
    edit(state)
    with pytest.raises(ContactbenchError, match=re.escape(expected)):
        NevergradSearch().load_state_dict(state)


def test_load_state_dict_never_unpickles(tmp_path):
    marker = tmp_path / "payload-ran"
    state = {
        **_valid_state(),
        "optimizer": torch.frombuffer(bytearray(pickle.dumps(_CreatesFile(marker))), dtype=torch.uint8),
    }
    with pytest.raises(ContactbenchError, match="unpickling"):
        NevergradSearch().load_state_dict(state)
    assert not marker.exists()


# ---------------------------------------------------------------- paths and bytes in a dataset


def _dataset(tmp_path: Path, n_frames: int = 6) -> Path:
    root = tmp_path / "ds"
    write_recordings(root, falling_cubes(n_trajectories=2, n_frames=n_frames))
    return root


def _edit_meta(root: Path, edit) -> None:
    meta = json.loads((root / "meta.json").read_text())
    edit(meta)
    (root / "meta.json").write_text(json.dumps(meta))


ESCAPING_PATHS = {
    "split up and out": (
        lambda m: m["splits"].update(train="../../../../etc/passwd"),
        "field 'splits.train' is '../../../../etc/passwd'",
    ),
    "split absolute": (lambda m: m["splits"].update(val="/etc/passwd"), "field 'splits.val' is '/etc/passwd'"),
    "split windows absolute": (lambda m: m["splits"].update(val="C:\\\\Windows\\\\win.ini"), "field 'splits.val'"),
    "split empty": (lambda m: m["splits"].update(test=""), "field 'splits.test' is ''"),
    "mesh up and out": (
        lambda m: m["bodies"][0].update(mesh="meshes/../../cube.obj"),
        r"bodies\[0\]: field 'mesh' is 'meshes/../../cube.obj'",
    ),
}


@pytest.mark.parametrize("case", sorted(ESCAPING_PATHS))
def test_paths_in_meta_json_stay_inside_the_dataset_folder(tmp_path, case):
    root = _dataset(tmp_path)
    edit, expected = ESCAPING_PATHS[case]
    _edit_meta(root, edit)
    with pytest.raises(RecordingsError, match=expected) as caught:
        read_recordings(root)
    message = str(caught.value)
    assert str(root / "meta.json") in message and "inside the dataset folder" in message and "pickl" not in message


def test_a_link_out_of_the_dataset_folder_is_refused(tmp_path):
    root = _dataset(tmp_path)
    outside = tmp_path / "elsewhere.npz"
    shutil.move(root / "train.npz", outside)
    os.symlink(outside, root / "train.npz")
    with pytest.raises(RecordingsError, match=r"field 'splits.train' is 'train.npz', which leads to .*elsewhere.npz"):
        read_recordings(root, ["train"])


def test_the_writer_refuses_paths_out_of_the_folder(tmp_path):
    dataset = falling_cubes()
    dataset.meta["splits"]["train"] = "../train.npz"
    with pytest.raises(RecordingsError, match="field 'splits.train'"):
        write_recordings(tmp_path / "ds", dataset)
    assert not (tmp_path / "train.npz").exists()


def _random_member(path: Path) -> None:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("poses.npy", np.random.default_rng(0).bytes(300))


NOT_NPZ = {
    "random bytes": (lambda p: p.write_bytes(np.random.default_rng(0).bytes(300)), "not an .npz archive (starts with"),
    "text": (lambda p: p.write_text("root:x:0:0:root:/root:/bin/bash\n"), "not an .npz archive (starts with b'root'"),
    "empty file": (lambda p: p.write_bytes(b""), "not an .npz archive"),
    "zip of random bytes": (_random_member, "field 'poses' is not an .npy array"),
    "truncated zip": (lambda p: p.write_bytes(p.read_bytes()[:200]), "not a readable .npz archive"),
}


@pytest.mark.parametrize("case", sorted(NOT_NPZ))
def test_bytes_that_are_not_an_npz_are_not_called_pickled(tmp_path, case):
    root = _dataset(tmp_path)
    corrupt, expected = NOT_NPZ[case]
    corrupt(root / "train.npz")
    with pytest.raises(RecordingsError, match=re.escape(expected)) as caught:
        read_recordings(root, ["train"])
    assert str(root / "train.npz") in str(caught.value) and "pickl" not in str(caught.value)


def test_an_escaping_split_path_is_one_clear_error_from_the_command_line(tmp_path):
    root = _dataset(tmp_path)
    _edit_meta(root, lambda m: m["splits"].update(test="../../../../etc/passwd"))
    result = run_entry_point(
        "evaluate.py",
        ["dataset=recordings", f"recordings={root}", f"hydra.run.dir={tmp_path / 'eval'}"],
        tmp_path,
        timeout=120,
    )
    assert_refused(result, str(root / "meta.json"), "field 'splits.test'", "inside the dataset folder")


# ------------------------------------------------ impossible settings, non-finite results, binary meshes


BAD_SETTINGS = {
    "negative sysid evaluations": (
        ["budget=smoke", "model=sysid", "model.budgets.smoke.evaluations=-16"],
        "model.budgets.smoke.evaluations is -16 (expected a positive integer)",
    ),
    "negative gnn steps": (
        ["budget=smoke", "model=gnn", "model.budgets.smoke.max_steps=-1"],
        "model.budgets.smoke.max_steps is -1 (expected a positive integer)",
    ),
    "zero batch": (
        ["budget=smoke", "model=sysid", "model.budgets.smoke.batch_trajectories=0"],
        "model.budgets.smoke.batch_trajectories is 0 (expected a positive integer or null (all))",
    ),
    "fractional restarts": (
        ["budget=smoke", "model=sysid", "model.budgets.smoke.restarts=1.5"],
        "model.budgets.smoke.restarts is 1.5",
    ),
    "negative learning rate": (
        ["budget=smoke", "model=gnn", "model.budgets.smoke.lr=-0.001"],
        "model.budgets.smoke.lr is -0.001 (expected a positive number)",
    ),
    "residual stage one": (
        ["budget=smoke", "model=residual", "model.budgets.smoke.search.restarts=0"],
        "model.budgets.smoke.search.restarts is 0 (expected a positive integer)",
    ),
    "a budget the model does not have": (
        ["model=gnn", "budget.name=tiny"],
        "model gnn has no budget 'tiny' (expected one of smoke, sensitivity, quick, paper in its config's budgets)",
    ),
    "zero diagnosis bootstrap": (["budget.diagnose.bootstrap=0"], "budget.diagnose.bootstrap is 0"),
    "no context frames": (["context_frames=0"], "context_frames is 0 (expected a positive integer)"),
    "zero threads": (["torch_threads=0"], "torch_threads is 0 (expected a positive integer or null (torch's choice))"),
    "zero frame stride": (
        ["observation.frame_stride=0"],
        "observation.frame_stride is 0 (expected a positive integer)",
    ),
    "negative friction": (
        ["friction=-1"],
        "scene 'frictioncubes': friction is -1 (expected a friction coefficient >= 0)",
    ),
    "restitution above one": (
        ["dataset=bouncycubes", "restitution=1.5"],
        "scene 'bouncycubes': restitution is 1.5 (expected a coefficient from 0 to 1)",
    ),
    "unknown solid": (["dataset=polyhedra", "faces=7"], "scene 'polyhedra': faces is 7 (expected one of"),
    "recordings unset": (["dataset=recordings"], "recordings is not set (expected recordings=... on the command line)"),
}


@pytest.mark.parametrize("case", sorted(BAD_SETTINGS))
def test_impossible_settings_are_refused_before_anything_runs(tmp_path, case):
    overrides, expected = BAD_SETTINGS[case]
    cfg = compose_config("train", overrides, tmp_path)
    with pytest.raises(ContactbenchError, match=re.escape(expected)):
        runs.train(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()


def test_a_custom_variant_says_it_is_one(tmp_path, caplog):
    checks.check(compose_config("train", ["friction=7"], tmp_path))
    assert "friction=7 is a custom variant, not one of the paper's Table 1 variants" in caplog.text
    caplog.clear()
    checks.check(compose_config("train", ["friction=0.75"], tmp_path))
    assert "custom variant" not in caplog.text


def test_a_direct_sysid_override_is_checked_by_the_module(small_recordings):
    from contactbench.models.sysid.module import SysIDModule

    with pytest.raises(
        ContactbenchError, match=re.escape("model.module.evaluations is -16 (expected a positive integer)")
    ):
        SysIDModule(
            small_recordings,
            6,
            evaluations=-16,
            restarts=1,
            num_workers=4,
            batch_trajectories=None,
            val_trajectories=None,
        )


@pytest.mark.parametrize(
    "script, overrides, expected",
    [
        ("diagnose.py", [], "error: recordings is not set (expected recordings=... on the command line)"),
        (
            "evaluate.py",
            ["dataset=recordings"],
            "error: recordings is not set (expected recordings=... on the command line)",
        ),
        (
            "train.py",
            ["budget=smoke", "model=sysid", "model.budgets.smoke.evaluations=-16"],
            "error: model.budgets.smoke.evaluations is -16 (expected a positive integer)",
        ),
        (
            "generate.py",
            ["friction=-1"],
            "error: scene 'frictioncubes': friction is -1 (expected a friction coefficient >= 0)",
        ),
    ],
)
def test_impossible_settings_are_one_line_from_the_command_line(tmp_path, script, overrides, expected):
    result = run_entry_point(script, overrides, tmp_path, timeout=120)
    assert assert_refused(result) == expected
    assert not (tmp_path / "data").exists()


def test_a_non_finite_metric_is_an_error_not_null(tmp_path):
    root = _dataset(tmp_path, n_frames=12)
    _edit_meta(root, lambda m: m.update(dt=1e300))  # valid by the format (a positive number), absurd in practice
    cfg = compose_config("evaluate", ["dataset=recordings", f"recordings={root}", "model=mujoco_default"], tmp_path)
    with pytest.raises(
        ContactbenchError,
        match=r"meta.json: test metric '\w+' of model 'mujoco_default' is nan \(expected a finite number",
    ):
        runs.evaluate(cfg, tmp_path / "eval")
    assert not (tmp_path / "eval" / "metrics.json").exists()


def test_a_binary_mesh_file_is_one_clear_error(tmp_path):
    root = _dataset(tmp_path)
    (root / "meshes" / "cube.obj").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(
        RecordingsError, match=r"cube.obj: not a text OBJ file \(byte 128 is not UTF-8.*\(meta.json bodies\[0\].mesh\)"
    ):
        read_recordings(root, ["train"])


# ---------------------------------------------------------------- bounded memory: sizes checked before allocating


_PEAK_PROBE = r"""
import json, resource, sys
from contactbench.recordings import RecordingsError, read_recordings

def status(field):  # this process's own figures; ru_maxrss would include the parent's size at fork
    for line in open("/proc/self/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024

# A regression must fail fast (MemoryError below), not take the machine's memory: 1 GiB of address space beyond now.
limit = status("VmSize") + (1 << 30)
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
before = status("VmHWM")
try:
    read_recordings(sys.argv[1], ["train"])
    outcome = "read"
except RecordingsError as error:
    outcome = "error: " + str(error)
after = status("VmHWM")
print(json.dumps({"outcome": outcome, "peak_mb": after / 2**20, "extra_mb": (after - before) / 2**20}))
"""


def read_in_subprocess(root: Path, timeout: float = 60) -> dict:
    """read_recordings(root, ['train']) in a fresh interpreter: its outcome and peak memory (MB, all and added)."""
    result = subprocess.run(
        [sys.executable, "-c", _PEAK_PROBE, str(root)], capture_output=True, text=True, timeout=timeout
    )
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def _npy_header(shape: tuple, dtype="<f8") -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def _deflate_bomb(path: Path, gigabytes: float = 2.0) -> None:
    """poses.npy of zeros, header and data agreeing, deflated: ~2 MB on disk that would inflate to ~2 GB."""
    n = int(gigabytes * 2**30) // (100 * 2 * 7 * 8)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as archive:
        with archive.open("poses.npy", "w", force_zip64=True) as member:
            member.write(_npy_header((n, 100, 2, 7)))
            zeros = bytes(1 << 24)
            left = n * 100 * 2 * 7 * 8
            while left:
                member.write(zeros[: min(left, len(zeros))])
                left -= min(left, len(zeros))


def _huge_header(path: Path) -> None:
    """A stored poses.npy whose header claims 10^12 trajectories, followed by a few bytes."""
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("poses.npy", _npy_header((10**12, 6, 2, 7)) + bytes(64))


def _lying_directory(path: Path) -> None:
    """A valid npz whose zip directory then claims a stored poses.npy of 2 GB (header patched to agree)."""
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("poses.npy", _npy_header((2**31 // 112, 1, 2, 7)) + bytes(64))
    data = bytearray(path.read_bytes())
    directory = data.index(b"PK\x01\x02")
    data[directory + 20 : directory + 28] = struct.pack("<II", 2**31, 2**31)  # compressed and uncompressed sizes
    path.write_bytes(bytes(data))


HUGE = {
    "deflate bomb": (_deflate_bomb, "field 'poses' inflates from"),
    "header claims 10^12 trajectories": (
        _huge_header,
        "field 'poses': its .npy header declares shape (1000000000000, 6, 2, 7)",
    ),
    "zip directory claims 2 GB": (
        _lying_directory,
        "field 'poses': its zip entry claims 2147483648 compressed bytes, more than the file's",
    ),
}
PEAK_EXTRA_MB = 64  # what reading a refused split may add to the interpreter's own memory


@pytest.mark.parametrize("case", sorted(HUGE))
def test_a_split_claiming_huge_arrays_is_refused_before_allocating(tmp_path, case, record_property):
    root = _dataset(tmp_path)
    build, expected = HUGE[case]
    build(root / "train.npz")
    assert (root / "train.npz").stat().st_size < 4 * 2**20
    probe = read_in_subprocess(root)
    record_property("peak_rss_mb", round(probe["peak_mb"], 1))
    assert probe["outcome"].startswith(f"error: {root / 'train.npz'}: ") and expected in probe["outcome"], probe[
        "outcome"
    ]
    assert "\n" not in probe["outcome"]
    assert probe["extra_mb"] < PEAK_EXTRA_MB, probe


def test_a_valid_split_still_reads_under_the_probe(tmp_path):
    probe = read_in_subprocess(_dataset(tmp_path))
    assert probe["outcome"] == "read", probe


MEMBER_LIES = {
    "data shorter than the header says": (
        lambda a: a.update(poses=_npy_header((2, 6, 2, 7)) + bytes(8)),
        "field 'poses': its .npy header declares shape (2, 6, 2, 7)",
    ),
    "data longer than the header says": (
        lambda a: a.update(poses=_npy_header((1, 6, 1, 7)) + bytes(8 * 2 * 6 * 7)),
        "field 'poses': its .npy header declares shape (1, 6, 1, 7)",
    ),
    "negative shape": (
        lambda a: a.update(poses=_npy_header((-2, -6, 1, 7)) + bytes(8 * 84)),
        "expected non-negative sizes",
    ),
    "structured dtype": (
        lambda a: a.update(poses=_npy_header((2,), [("a", "<f8")]) + bytes(16)),
        "field 'poses' has dtype",
    ),
    "string dtype": (
        lambda a: a.update(lengths=_npy_header((2,), "<U4") + bytes(32)),
        "field 'lengths' has dtype <U4 (expected a plain numeric array)",
    ),
    "header too long": (
        lambda a: a.update(poses=b"\x93NUMPY\x01\x00" + struct.pack("<H", 60000) + b" " * 60000),
        "field 'poses' is not a readable .npy array",
    ),
    "unknown npy version": (
        lambda a: a.update(poses=b"\x93NUMPY\x09\x00" + bytes(100)),
        "unsupported .npy format version (9, 0)",
    ),
}


@pytest.mark.parametrize("case", sorted(MEMBER_LIES))
def test_an_npy_header_that_disagrees_with_its_member_is_refused(tmp_path, case):
    root = _dataset(tmp_path)
    edit, expected = MEMBER_LIES[case]
    with zipfile.ZipFile(root / "train.npz") as archive:
        members = {name[:-4]: archive.read(name) for name in archive.namelist()}
    edit(members)
    with zipfile.ZipFile(root / "train.npz", "w") as archive:
        for name, payload in members.items():
            archive.writestr(f"{name}.npy", payload)
    with pytest.raises(RecordingsError, match=re.escape(expected)) as caught:
        read_recordings(root, ["train"])
    assert str(caught.value).startswith(f"{root / 'train.npz'}: ") and "\n" not in str(caught.value)


# ---------------------------------------------------------------- leftovers of a killed write, too-short trajectories


def test_stale_staging_folders_are_removed_at_the_next_write_and_only_those(tmp_path):
    from contactbench import atomic

    root = _dataset(tmp_path)
    host = atomic._owner().rsplit("-", 1)[0]
    dead = subprocess.Popen(["true"])  # a process that is gone: its pid names a dead writer
    dead.wait()
    alive = subprocess.Popen(["sleep", "60"])
    try:
        names = {
            "dead writer": f".ds.{host}-{dead.pid}.abcd1234.tmp",
            "live writer": f".ds.{host}-{alive.pid}.abcd1234.tmp",
            "other host, recent": f".ds.elsewhere-{dead.pid}.abcd1234.tmp",
            "old naming, recent": ".ds.k3j9x_2a.tmp",
            "old naming, a day old": ".ds.q8w7e6r5.tmp",
            "another dataset's": f".other.{host}-{dead.pid}.abcd1234.tmp",
            "not our pattern": ".ds.notes.tmp",
        }
        for name in names.values():
            (tmp_path / name / "meshes").mkdir(parents=True)
            (tmp_path / name / "train.npz").write_bytes(b"half written")
        day_old = time.time() - atomic.STALE_AFTER_S - 60
        for path in [
            tmp_path / names["old naming, a day old"],
            *(tmp_path / names["old naming, a day old"]).rglob("*"),
        ]:
            os.utime(path, (day_old, day_old))
        write_recordings(root, falling_cubes(n_trajectories=2, n_frames=6))
        left = {label for label, name in names.items() if (tmp_path / name).exists()}
        assert left == {
            "live writer",
            "other host, recent",
            "old naming, recent",
            "another dataset's",
            "not our pattern",
        }
        assert read_recordings(root).splits["train"].n_trajectories == 2
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".ds.") and p.name not in names.values()]
    finally:
        alive.kill()
        alive.wait()


def test_a_generation_killed_during_its_final_write_is_cleaned_by_the_next(tmp_path):
    """A real kill: the writer is SIGKILLed while its staging folder exists; the next write of that dataset removes
    it."""
    script = (
        "import os, signal, sys\n"
        "sys.path.insert(0, sys.argv[2])\n"
        "from conftest import falling_cubes\n"
        "from contactbench import atomic, recordings\n"
        "real = atomic.write_json\n"
        "def killed(path, obj):\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
        "atomic.write_json = killed  # meta.json is the last file of the final write\n"
        "recordings.write_recordings(sys.argv[1], falling_cubes())\n"
    )
    root = tmp_path / "friction=0.5"
    result = subprocess.run(
        [sys.executable, "-c", script, str(root), str(Path(__file__).parent)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == -9, result.stderr[-2000:]
    leftovers = [p for p in tmp_path.iterdir() if p.name.startswith(".friction=0.5.") and p.name.endswith(".tmp")]
    assert len(leftovers) == 1 and not root.exists()
    write_recordings(root, falling_cubes())
    assert not leftovers[0].exists() and sorted(p.name for p in tmp_path.iterdir()) == ["friction=0.5"]


def test_too_short_trajectories_name_the_file_and_write_nothing(tmp_path):
    root = tmp_path / "ds"
    write_recordings(root, falling_cubes(n_trajectories=2, n_frames=6))  # 6 frames: all context, nothing to predict
    run_dir = tmp_path / "run"
    cfg = compose_config("train", ["model=mujoco_default", "dataset=recordings", f"recordings={root}"], tmp_path)
    with pytest.raises(
        RecordingsError,
        match=re.escape(
            f"{root / 'train.npz'}: field 'lengths': trajectory 0 has 6 frames (2 of 2 have fewer than 7; expected "
            "at least 7: context_frames=6"
        ),
    ):
        runs.train(cfg, run_dir)
    assert not run_dir.exists()


def test_too_short_trajectories_are_one_line_from_the_command_line(tmp_path):
    root = tmp_path / "ds"
    write_recordings(root, falling_cubes(n_trajectories=2, n_frames=6))
    run_dir = tmp_path / "eval"
    run_dir.mkdir()
    result = run_entry_point(
        "evaluate.py",
        ["dataset=recordings", f"recordings={root}", "model=mujoco_default", f"hydra.run.dir={run_dir}"],
        tmp_path,
        timeout=120,
    )
    assert_refused(result, str(root / "test.npz"), "field 'lengths'", "expected at least 7")
    assert tree_digest(run_dir) == {}


# ---------------------------------------------------------------- misspelled new keys, the README's quoting rule


@pytest.mark.parametrize("task", ["train", "evaluate", "generate", "diagnose"])
def test_a_misspelled_new_top_level_key_is_refused(tmp_path, task):
    overrides = ["+contxt_frames=3"] + (["recordings=x"] if task == "diagnose" else [])
    cfg = compose_config(task, overrides, tmp_path)
    message = checks.unknown_addition(cfg, overrides)
    assert message is not None and message.startswith(f"+contxt_frames=... adds a setting {task} does not read (")
    if task != "generate":
        assert "did you mean context_frames=...?" in message


def test_known_additions_and_other_overrides_are_accepted(tmp_path):
    overrides = ["+effects=[floor_tilt]", "+effect_strength=2", "friction=0.25", "++seed=3"]
    assert checks.unknown_addition(compose_config("generate", overrides, tmp_path), overrides) is None
    overrides = ["+overwrite=true", "model=sysid", "+model.module.extra=1"]  # nested keys: not top-level, left alone
    assert checks.unknown_addition(compose_config("train", overrides[:2], tmp_path), overrides) is None


def test_a_misspelled_new_key_is_one_line_from_the_command_line_and_writes_nothing(tmp_path):
    run_dir = tmp_path / "run"
    result = run_entry_point("train.py", ["+contxt_frames=3", f"hydra.run.dir={run_dir}"], tmp_path, timeout=120)
    assert_refused(result, "+contxt_frames=... adds a setting train does not read (did you mean context_frames=...?")
    assert not run_dir.exists() and not (tmp_path / "outputs").exists()


def test_the_readme_diagnose_example_with_commas_parses():
    import shlex

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    lines = [line for line in readme.splitlines() if line.startswith("python diagnose.py") and "," in line]
    assert lines, "the README's diagnose example with a comma in the path"
    for line in lines:
        arguments = shlex.split(line.split("  #")[0])[2:]  # what the shell hands to diagnose.py
        cfg = compose_config("diagnose", arguments, Path("/tmp"))
        assert cfg.recordings == "data/frictioncubes/friction=0.5,effects=floor_tilt,strength=2"
    assert (
        compose_config("diagnose", ["recordings='my data/a,b=1 \\'c\\''"], Path("/tmp")).recordings
        == "my data/a,b=1 'c'"
    )


# ---------------------------------------------------------------- property-based fuzzing of the reader


def _valid_files() -> dict[str, bytes]:
    """A valid small dataset's files (meta.json, meshes/cube.obj, train.npz), as bytes."""
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "ds"
        write_recordings(root, falling_cubes(n_trajectories=2, n_frames=5, n_bodies=2))
        return {
            str(p.relative_to(root)): p.read_bytes()
            for p in root.rglob("*")
            if p.is_file() and p.name != "val.npz" and p.name != "test.npz"
        }


VALID = _valid_files()
JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.sampled_from(
        ["", "train.npz", "../train.npz", "/etc/passwd", "meshes/cube.obj", "rigid-contact-recordings", "a\x00b", "\\x"]
    ),
    lambda children: (
        st.lists(children, max_size=4)
        | st.dictionaries(st.sampled_from(["train", "name", "mesh", "mass", "x"]), children, max_size=3)
    ),
    max_leaves=6,
)
META_PLACES = [
    "format",
    "version",
    "name",
    "dt",
    "gravity",
    "floor_z",
    "bodies",
    "splits",
    "splits.train",
    "bodies.0",
    "bodies.0.mesh",
    "bodies.0.mass",
    "bodies.0.inertia_diagonal",
    "bodies.1.name",
    "gravity.2",
]


def _edit_place(meta: dict, place: str, value, delete: bool) -> None:
    *parents, last = place.split(".")
    node = meta
    for part in parents:
        node = node[int(part)] if isinstance(node, list) else node[part]
    key = int(last) if isinstance(node, list) else last
    if delete:
        del node[key]
    else:
        node[key] = value


def _members(payload: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(payload)) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def _zipped(members: dict[str, bytes], compression: int) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buffer.getvalue()


BYTE_EDITS = st.lists(
    st.tuples(st.integers(min_value=0, max_value=10**6), st.integers(min_value=0, max_value=255)),
    min_size=1,
    max_size=6,
)
MUTATIONS = st.one_of(
    st.tuples(st.just("meta field"), st.sampled_from(META_PLACES), JSON_VALUES, st.booleans()),
    st.tuples(st.just("npz bytes"), BYTE_EDITS, st.integers(min_value=0, max_value=10**6)),  # flips, then cut at
    st.tuples(
        st.just("npy member"),
        st.sampled_from(["poses.npy", "lengths.npy", "velocities.npy", "source_index.npy"]),
        BYTE_EDITS,
        st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]),
    ),
    st.tuples(
        st.just("npy header"),
        st.sampled_from(["poses.npy", "lengths.npy"]),
        st.sampled_from(["shape", "descr", "fortran_order"]),
        st.sampled_from(
            [
                "(1000000000000, 5, 2, 7)",
                "(-1,)",
                "()",
                "'<f4'",
                "'|O'",
                "'>f8'",
                "True",
                "(2, 5, 2, 7, 1)",
                "'<c16'",
                "'<i8'",
                "(0, 5, 2, 7)",
                "[1]",
            ]
        ),
    ),
    st.tuples(st.just("mesh bytes"), BYTE_EDITS),
)


def _apply(files: dict[str, bytes], mutation) -> dict[str, bytes]:
    files = dict(files)
    kind = mutation[0]
    if kind == "meta field":
        _, place, value, delete = mutation
        meta = json.loads(files["meta.json"])
        try:
            _edit_place(meta, place, value, delete)
        except (KeyError, IndexError, TypeError):
            pass
        files["meta.json"] = json.dumps(meta).encode()
    elif kind in ("npz bytes", "mesh bytes"):
        name = "train.npz" if kind == "npz bytes" else "meshes/cube.obj"
        data = bytearray(files[name])
        for position, value in mutation[1]:
            data[position % len(data)] = value
        if kind == "npz bytes":
            data = data[: max(1, mutation[2] % (len(data) + 1))]
        files[name] = bytes(data)
    elif kind == "npy member":
        _, member, edits, compression = mutation
        members = _members(files["train.npz"])
        data = bytearray(members[member])
        for position, value in edits:
            data[position % len(data)] = value
        members[member] = bytes(data)
        files["train.npz"] = _zipped(members, compression)
    elif kind == "npy header":
        _, member, field, value = mutation
        members = _members(files["train.npz"])
        array = np.lib.format.read_array(io.BytesIO(members[member]))
        header = {
            "descr": repr(np.lib.format.dtype_to_descr(array.dtype)),
            "fortran_order": "False",
            "shape": repr(array.shape),
        }
        header[field] = value  # the header is Python literal text: written as is, right or wrong
        text = "{" + "".join(f"'{key}': {text}, " for key, text in header.items()) + "}"
        text += " " * (-(len(text) + 11) % 64) + "\n"
        buffer = io.BytesIO(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode("latin1"))
        members[member] = buffer.getvalue() + array.tobytes()
        files["train.npz"] = _zipped(members, zipfile.ZIP_STORED)
    return files


@hypothesis_settings(
    max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow], database=None
)
@given(MUTATIONS)
def test_fuzzed_datasets_read_or_give_one_recordings_error(mutation):
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "ds"
        for name, data in _apply(VALID, mutation).items():
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            (root / name).write_bytes(data)
        try:
            dataset = read_recordings(root, ["train"])
        except RecordingsError as error:
            message = str(error)
            assert message.startswith(str(root)) and "\n" not in message and "Traceback" not in message, message
        else:
            split = dataset.splits["train"]
            assert split.poses.dtype == np.float64 and split.lengths.dtype == np.int64
            assert np.isfinite(split.poses[split.valid_mask()]).all()


@pytest.mark.parametrize(
    "script, overrides, needle",
    [
        ("train.py", ["budget=-1"], "budget=-1: budget is a config group (expected one of paper, quick"),
        ("train.py", ["model=nosuch"], "model=nosuch: model has no option nosuch (expected one of bullet_default"),
        ("evaluate.py", ["-m", "model=1,2"], "model=1,2: model is a config group (expected one of"),
        ("generate.py", ["variant=["], "cannot parse an override:"),
    ],
)
def test_an_override_hydra_cannot_take_is_one_line_not_a_traceback(tmp_path, script, overrides, needle):
    result = run_entry_point(script, overrides, tmp_path, timeout=120)
    assert result.returncode == 2 and needle in result.stderr, result.stderr[-2000:]
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "outputs").exists()  # refused before Hydra made a run folder


@pytest.mark.parametrize(
    "task, arguments, line",
    [
        (
            "train",
            ["budget=quik"],
            "budget=quik: budget has no option quik (did you mean quick? expected one of paper,",
        ),
        (
            "evaluate",
            ["hydra/launcher=lokal"],
            "hydra/launcher=lokal: hydra/launcher has no option lokal (did you mean",
        ),
        (
            "train",
            ["-m", "model=gnn,sysd"],
            "model=sysd: model has no option sysd (did you mean sysid? expected one of",
        ),
        ("train", ["-m", "variant=glob(frictioncubes_*)", "model=gnn,nosuch"], "model=nosuch: model has no option"),
        ("train", ["contxt_frames=3"], "contxt_frames=3: the config has no contxt_frames to override (did you mean"),
        (
            "train",
            ["model=sysid", "model.module.evaluatons=3"],
            "the config has no model.module.evaluatons to override (did you mean model.module.evaluations=...?",
        ),
        ("train", ["-m", "contxt_frames=3,4"], "contxt_frames=3,4: the config has no contxt_frames to override"),
        ("generate", ["model=gnn,sysid"], "Ambiguous value for argument 'model=gnn,sysid'; 1. To use it as a list"),
    ],
)
def test_what_hydra_would_refuse_with_a_page_is_one_line(capsys, task, arguments, line):
    """Composed as Hydra composes it, in this process: a sweep's every group option and its first job are checked."""
    with pytest.raises(SystemExit) as stopped:
        cli.check_command_line(task, arguments)
    err = capsys.readouterr().err
    assert stopped.value.code == 2 and len(err.strip().splitlines()) == 1 and line in err, err


@pytest.mark.parametrize(
    "task, arguments",
    [
        ("train", ["-m", "experiment=matrix", "seed=range(3)"]),
        ("train", ["-m", "model=ballistic,sysid", f"hydra.searchpath=[file://{EXTERNAL_CONF}]", "variant=glob(*)"]),
        ("generate", ["variant=frictioncubes_0.5", "+effects=[floor_tilt]", "+effect_strength=2"]),
        ("diagnose", ["recordings=assets/contactnets_cube", "--help"]),
    ],
)
def test_commands_hydra_takes_pass_the_check(capsys, task, arguments):
    cli.check_command_line(task, arguments)
    assert capsys.readouterr().err == ""
