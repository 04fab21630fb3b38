"""A split's .npz read without trusting it: every size a zip directory or .npy header declares is checked before
anything is decompressed or allocated, and only plain numeric arrays are read (nothing unpickled)."""

from __future__ import annotations

import lzma
import math
import os
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from contactbench.errors import RecordingsError
from contactbench.recordings_validation import fail, validate_split
from contactbench.scene import Split

ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a zip's first entry, or an empty zip
# Bounds checked before a member is decompressed or allocated: a few kB of crafted zip must not claim gigabytes.
MAX_INFLATION = 100  # uncompressed / compressed size of a deflated member; trajectories compress ~1.2x, a bomb ~1000x
INFLATION_FREE_BYTES = 1 << 20  # members this small may compress as well as they like
NPY_MAGIC = b"\x93NUMPY"
NUMERIC_KINDS = "biufc"  # bool, integers, floats, complex: plain numbers, nothing to unpickle or interpret
_CHUNK = 1 << 24


def memory_limit() -> int:
    """The most bytes one split may declare: this machine's physical memory (a larger split cannot be read here)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 1 << 36


def _first_line(error: BaseException) -> str:
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__


def _npz_members(archive: zipfile.ZipFile, path: Path, where: str) -> dict[str, zipfile.ZipInfo]:
    """The archive's members by field name (np.load's naming: '.npy' dropped), their sizes checked against the file."""
    file_size = path.stat().st_size
    members: dict[str, zipfile.ZipInfo] = {}
    declared = 0
    for info in archive.infolist():
        name = info.filename[: -len(".npy")] if info.filename.endswith(".npy") else info.filename
        if info.is_dir():
            continue
        if info.compress_size > file_size:
            raise fail(
                where,
                f"field '{name}': its zip entry claims {info.compress_size} compressed bytes, more than the file's "
                f"{file_size} (expected an intact archive)",
            )
        if info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size:
            raise fail(
                where,
                f"field '{name}': its stored zip entry claims {info.file_size} bytes but holds {info.compress_size} "
                "(expected an intact archive)",
            )
        if info.file_size > INFLATION_FREE_BYTES and info.file_size > MAX_INFLATION * max(info.compress_size, 1):
            raise fail(
                where,
                f"field '{name}' inflates from {info.compress_size} to {info.file_size} bytes "
                f"(more than {MAX_INFLATION}x; expected recorded trajectories, not a decompression bomb)",
            )
        members[name] = info
        declared += info.file_size
    limit = memory_limit()
    if declared > limit:
        raise fail(
            where,
            f"its arrays declare {declared} bytes, more than this machine's {limit} bytes of memory (expected a "
            "split that fits in memory)",
        )
    return members


def _float_array(archive: zipfile.ZipFile, members: Mapping[str, zipfile.ZipInfo], name: str, where: str) -> np.ndarray:
    array = _member(archive, members, name, where)
    if not np.issubdtype(array.dtype, np.floating):
        raise fail(where, f"field '{name}' has dtype {array.dtype} (expected float64)")
    return array.astype(np.float64, copy=False)


def _member(archive: zipfile.ZipFile, members: Mapping[str, zipfile.ZipInfo], name: str, where: str) -> np.ndarray:
    """One .npy member as a plain numeric array, or a RecordingsError that says what it is instead.

    The .npy header is read first and its shape and dtype checked against the member's size in the zip directory
    (header plus data, exactly), so nothing is allocated or decompressed beyond what the header and directory agree on.
    """
    info = members[name]
    with archive.open(info) as handle:
        if not info.filename.endswith(".npy") or handle.read(len(NPY_MAGIC)) != NPY_MAGIC:
            raise fail(where, f"field '{name}' is not an .npy array (no .npy header; expected a plain numeric array)")
        try:
            version = (ord(handle.read(1) or b"\xff"), ord(handle.read(1) or b"\xff"))
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(handle)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(handle)
            else:
                raise ValueError(f"unsupported .npy format version {version}")
        except Exception as error:  # numpy parses the header text as a Python literal: any failure there is this one
            raise fail(where, f"field '{name}' is not a readable .npy array ({_first_line(error)})") from None
        if dtype.hasobject:
            raise fail(
                where, f"field '{name}' cannot be read without unpickling (object data); arrays must be plain numeric"
            )
        if dtype.kind not in NUMERIC_KINDS or dtype.fields is not None or dtype.subdtype is not None:
            raise fail(where, f"field '{name}' has dtype {dtype} (expected a plain numeric array)")
        if any(n < 0 for n in shape):
            raise fail(where, f"field '{name}': its .npy header declares shape {shape} (expected non-negative sizes)")
        count = math.prod(shape)
        expected = handle.tell() + count * dtype.itemsize
        if expected != info.file_size:
            raise fail(
                where,
                f"field '{name}': its .npy header declares shape {shape} {dtype} ({count * dtype.itemsize} bytes of "
                f"data) but the member holds {info.file_size} bytes in all (expected header and data to agree)",
            )
        array = np.empty(count, dtype=dtype)
        raw = array.view(np.uint8)
        for start in range(0, raw.size, _CHUNK):
            chunk = handle.read(min(_CHUNK, raw.size - start))
            if len(chunk) != min(_CHUNK, raw.size - start):
                raise fail(where, f"field '{name}' ends early (expected {raw.size} bytes of data)")
            raw[start : start + len(chunk)] = np.frombuffer(chunk, dtype=np.uint8)
    if not dtype.isnative:
        array = array.astype(dtype.newbyteorder("="))
    return array.reshape(shape, order="F" if fortran else "C")


def read_split(path: Path, n_bodies: int) -> Split:
    where = str(path)
    if not path.is_file():
        raise RecordingsError(f"{path}: split file missing (named in meta.json 'splits')")
    with open(path, "rb") as handle:
        magic = handle.read(4)
    if magic not in ZIP_MAGIC:  # np.load would call any other bytes "pickled data"
        raise fail(where, f"not an .npz archive (starts with {magic!r}; expected a zip archive of .npy arrays)")
    try:
        with zipfile.ZipFile(path) as archive:
            members = _npz_members(archive, path, where)
            if "poses" not in members:
                raise fail(where, "field 'poses' is missing (expected float64 [N, T, K, 7])")
            poses = _float_array(archive, members, "poses", where)
            if "lengths" in members:
                lengths = _member(archive, members, "lengths", where)
                if not np.issubdtype(lengths.dtype, np.integer):
                    raise fail(where, f"field 'lengths' has dtype {lengths.dtype} (expected int64)")
                lengths = lengths.astype(np.int64)
            else:
                lengths = np.full(
                    poses.shape[0] if poses.ndim else 0, poses.shape[1] if poses.ndim > 1 else 0, dtype=np.int64
                )
            velocities = _float_array(archive, members, "velocities", where) if "velocities" in members else None
            extras = {
                name: _member(archive, members, name, where)
                for name in members
                if name not in ("poses", "lengths", "velocities")
            }
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        NotImplementedError,
        OSError,
        EOFError,
        RuntimeError,
        zlib.error,
        lzma.LZMAError,
    ) as error:
        raise fail(where, f"not a readable .npz archive ({_first_line(error)})") from None
    except ValueError as error:
        if isinstance(error, RecordingsError):
            raise
        raise fail(where, f"not a readable .npz archive ({_first_line(error)})") from None
    split = Split(poses, lengths, velocities, extras)
    validate_split(split, n_bodies, where)
    return split
