"""The one reader and writer of the recordings format (docs/RECORDINGS.md, versions 1 and 2): a dataset folder read
and checked into Recordings (scene.py), or Recordings checked and written into a folder in one swap. The rules it
checks: recordings_validation.py; a split's .npz: recordings_npz.py."""

from __future__ import annotations

import copy
import json
import os
import shutil
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from contactbench import atomic
from contactbench.errors import RecordingsError
from contactbench.meshes import Mesh, MeshError, obj_text, read_obj
from contactbench.recordings_npz import read_split
from contactbench.recordings_validation import (
    check_convex_parts,
    mesh_fields,
    mesh_paths,
    validate_hinges,
    validate_meta,
    validate_split,
)
from contactbench.scene import Recordings, Scene

# A model's documented imports (docs/ADDING_A_MODEL.md): `from contactbench.recordings import Recordings, Scene`.
__all__ = [
    "Recordings",
    "RecordingsError",
    "Scene",
    "read_meta",
    "read_recordings",
    "require_frames",
    "write_recordings",
]


def read_meta(root: str | os.PathLike) -> dict:
    path = Path(root) / "meta.json"
    if not Path(root).is_dir():
        raise RecordingsError(f"{root}: not a dataset folder (expected a folder with meta.json)")
    if not path.is_file():
        raise RecordingsError(f"{path}: missing (every recordings dataset needs meta.json)")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise RecordingsError(f"{path}: not valid JSON ({error})") from None
    validate_meta(meta, str(path))
    return meta


def read_recordings(root: str | os.PathLike, splits: Iterable[str] | None = None) -> Recordings:
    """Read and validate a dataset folder; `splits` limits which split files are loaded (default: all)."""
    root = Path(root)
    meta = read_meta(root)
    meshes: dict[str, Mesh] = {}
    for relative, named_by in mesh_fields(meta):
        if relative in meshes:
            continue
        mesh_path = _inside(root, relative, named_by)
        if not mesh_path.is_file():
            raise RecordingsError(f"{mesh_path}: mesh file missing (meta.json {named_by})")
        try:
            meshes[relative] = read_obj(mesh_path)
        except MeshError as error:
            raise RecordingsError(f"{error} (meta.json {named_by})") from None
    check_convex_parts(meta, meshes, str(root / "meta.json"))
    wanted = list(meta["splits"]) if splits is None else list(splits)
    unknown = [name for name in wanted if name not in meta["splits"]]
    if unknown:
        raise RecordingsError(
            f"{root / 'meta.json'}: field 'splits' has no split {unknown[0]!r} (it has {sorted(meta['splits'])})"
        )
    loaded = {
        name: read_split(_inside(root, meta["splits"][name], f"splits.{name}"), len(meta["bodies"])) for name in wanted
    }
    recordings = Recordings(meta=meta, meshes=meshes, splits=loaded, root=root)
    for name, split in loaded.items():
        validate_hinges(recordings, split, str(root / meta["splits"][name]))
    return recordings


def require_frames(recordings: Recordings, minimum: int, reason: str) -> None:
    """Every loaded trajectory has at least `minimum` frames, or one RecordingsError naming the split file."""
    for name, split in recordings.splits.items():
        short = np.flatnonzero(split.lengths < minimum)
        if len(short):
            where = (
                recordings.root / recordings.meta["splits"][name]
                if recordings.root is not None
                else f"{recordings.name} split {name!r}"
            )
            raise RecordingsError(
                f"{where}: field 'lengths': trajectory {short[0]} has {split.lengths[short[0]]} frames "
                f"({len(short)} of {split.n_trajectories} have fewer than {minimum}; expected at least {minimum}: "
                f"{reason})"
            )


def _inside(root: Path, relative: str, field: str) -> Path:
    """A meta.json path, refused if a link leads it out of the dataset folder (validate_meta caught '..' already)."""
    path = root / relative
    if not path.resolve().is_relative_to(root.resolve()):
        raise RecordingsError(
            f"{root / 'meta.json'}: field '{field}' is {relative!r}, which leads to {path.resolve()} "
            "(expected a file inside the dataset folder, not a link out of it)"
        )
    return path


def _inside_path_checked(name: str) -> str:
    """An extra file's name, refused if it would leave the dataset folder."""
    if Path(name).is_absolute() or ".." in Path(name).parts:
        raise RecordingsError(f"extra file {name!r}: expected a path inside the dataset folder")
    return name


def write_recordings(
    root: str | os.PathLike, recordings: Recordings, extra_files: Mapping[str, str] | None = None
) -> Path:
    """Validate, then write the whole dataset into a staging folder and swap it into place; `extra_files` ({name:
    text}, e.g. a LICENSE) go into the same folder in the same swap."""
    root = Path(root)
    meta = copy.deepcopy(recordings.meta)
    validate_meta(meta, f"{root / 'meta.json'} (being written)")
    missing = [path for path in mesh_paths(meta) if path not in recordings.meshes]
    if missing:
        raise RecordingsError(f"{root / 'meta.json'} (being written): no mesh given for {missing[0]!r}")
    check_convex_parts(meta, recordings.meshes, f"{root / 'meta.json'} (being written)")
    for name, split in recordings.splits.items():
        if name not in meta["splits"]:
            raise RecordingsError(f"{root / 'meta.json'} (being written): split {name!r} not listed in 'splits'")
        validate_split(split, len(meta["bodies"]), f"{root / meta['splits'][name]} (being written)")
        validate_hinges(recordings, split, f"{root / meta['splits'][name]} (being written)")
    atomic.remove_stale_staging(root)  # left by a writer killed during its final write
    staging = atomic.staging_directory(root)
    try:
        for mesh_path in mesh_paths(meta):
            atomic.write_text(staging / mesh_path, obj_text(recordings.meshes[mesh_path]))
        for name, split in recordings.splits.items():
            atomic.write_npz(staging / meta["splits"][name], split.arrays())
        for name, text in (extra_files or {}).items():
            atomic.write_text(staging / _inside_path_checked(name), text)
        atomic.write_json(staging / "meta.json", meta)
        atomic.replace_directory(staging, root)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return root
