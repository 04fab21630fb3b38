"""Atomic, byte-reproducible file writes: temp file in the same folder, then rename."""

from __future__ import annotations

import io
import json
import logging
import os
import re
import shutil
import socket
import tempfile
import time
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

# Fixed zip timestamps: np.savez stamps the wall clock, which would make equal data differ byte-wise.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def write_bytes(path: str | os.PathLike, payload: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(payload)
        os.chmod(tmp, 0o644)  # mkstemp creates owner-only files; datasets and reports are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n")


def npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """An .npz archive (readable by np.load) whose bytes depend only on the arrays."""
    buffer = io.BytesIO()
    # Stored, not deflated: float data compresses little, and deflate slowed the generator down markedly.
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
        for name in sorted(arrays):
            array_buffer = io.BytesIO()
            np.lib.format.write_array(array_buffer, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.compress_type = zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            archive.writestr(info, array_buffer.getvalue())
    return buffer.getvalue()


def write_npz(path: str | os.PathLike, arrays: Mapping[str, np.ndarray]) -> None:
    write_bytes(path, npz_bytes(arrays))


def replace_directory(staging: Path, target: Path) -> None:
    """Swap a fully written staging folder into place; readers never see a half-written target."""
    target = Path(target)
    if target.exists():
        retired = target.with_name(f".{target.name}.old-{os.getpid()}")
        os.replace(target, retired)
        os.replace(staging, target)
        shutil.rmtree(retired, ignore_errors=True)
    else:
        os.replace(staging, target)


def _owner() -> str:
    """Who stages a folder: host and process, so a later writer can tell a dead writer's leftovers from a live one's."""
    host = re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}"


def staging_directory(target: str | os.PathLike) -> Path:
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.{_owner()}.", suffix=".tmp", dir=target.parent))
    staging.chmod(0o755)
    return staging


STALE_AFTER_S = 24 * 3600  # a staging folder untouched this long is a leftover, whoever made it


def remove_stale_staging(target: str | os.PathLike) -> list[Path]:
    """Remove staging folders of `target` that a killed writer left (`.<name>.<host>-<pid>.<random>.tmp`).

    Only folders of exactly this pattern, next to `target`: stale when their process is gone (same host), or when
    nothing in them changed for STALE_AFTER_S (another host, or the older `.<name>.<random>.tmp` naming).
    """
    target = Path(target)
    if not target.parent.is_dir():
        return []
    pattern = re.compile(
        rf"\.{re.escape(target.name)}\.(?:(?P<host>[A-Za-z0-9_-]+)-(?P<pid>\d+)\.)?[A-Za-z0-9_]{{8}}\.tmp"
    )
    host = _owner().rsplit("-", 1)[0]
    removed = []
    for path in target.parent.iterdir():
        match = pattern.fullmatch(path.name)
        if not match or path.is_symlink() or not path.is_dir():
            continue
        if match["pid"] and match["host"] == host and int(match["pid"]) != os.getpid():
            stale = not _alive(int(match["pid"]))
        else:
            stale = time.time() - _newest_change(path) > STALE_AFTER_S
        if stale:
            shutil.rmtree(path, ignore_errors=True)
            log.info("removed %s, a staging folder left by an interrupted write", path)
            removed.append(path)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def _newest_change(path: Path) -> float:
    newest = path.lstat().st_mtime
    for child in path.rglob("*"):
        try:
            newest = max(newest, child.lstat().st_mtime)
        except OSError:
            pass
    return newest
