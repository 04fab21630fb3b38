"""What the Hydra configs rely on: where they live (REPO_ROOT, CONFIG_DIR) and the `cb.*` OmegaConf resolvers they
call (stable variant and run-folder names, the search's step count, whether a person watches). Registered on import of
contactbench; checking a composed config is checks.py's."""

from __future__ import annotations

import functools
import hashlib
import json
import os
import sys
from pathlib import Path

from omegaconf import OmegaConf

REPO_ROOT = Path(__file__).resolve().parents[2]
CONFIG_DIR = REPO_ROOT / "conf"


def format_value(value) -> str:
    """0 and 0.0 name the same variant folder: numbers print in their shortest form ('0', '0.25', '1')."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    return f"{value:g}"


def generations(evaluations: int, num_workers: int, restarts: int) -> int:
    """Optimiser generations (training steps) of a search: ceil(evaluations / num_workers) per restart."""
    return -(-int(evaluations) // int(num_workers)) * int(restarts)


def observed(noise_mm, frame_stride) -> str:
    """The run-folder suffix of an observation: nothing for the recordings as they are."""
    if float(noise_mm) == 0 and int(frame_stride) == 1:
        return ""
    return f",noise_mm={format_value(noise_mm)},frame_stride={int(frame_stride)}"


def recordings_key(path) -> str:
    """A recordings folder's run-folder name: its own name and a short hash of its files' bytes (meta.json, the
    splits and meshes it names), so two datasets that share a folder name (~/a/mycube, ~/b/mycube) never share a run
    folder, and the same files under another path do. A folder without a readable meta.json keeps its bare name:
    the reader, not a resolver, says what is wrong with it."""
    root = Path(str(path))
    try:
        meta_bytes = (root / "meta.json").read_bytes()
        files = ["meta.json", *sorted(_named_files(json.loads(meta_bytes)))]
        stamps = tuple((name, (root / name).stat().st_size, (root / name).stat().st_mtime_ns) for name in files)
    except (OSError, ValueError):
        return root.name
    return f"{root.name}-{_files_digest(str(root.resolve()), stamps)}"


def _named_files(meta) -> set[str]:
    """The split and mesh files a meta.json names (read before it is validated: what is not a name is skipped)."""
    names = set((meta.get("splits") or {}).values()) if isinstance(meta, dict) else set()
    for entry in [*(meta.get("bodies") or []), *(meta.get("static") or [])] if isinstance(meta, dict) else []:
        if isinstance(entry, dict):
            names.update([entry.get("mesh"), *(entry.get("pieces") or [])])
    return {name for name in names if isinstance(name, str)}


@functools.lru_cache(maxsize=64)
def _files_digest(root: str, stamps: tuple) -> str:
    """Cached by the files' sizes and times: a config resolves its run folder's name several times."""
    digest = hashlib.sha256()
    for name, _, _ in stamps:
        digest.update(name.encode() + b"\0" + (Path(root) / name).read_bytes() + b"\0")
    return digest.hexdigest()[:8]


def interactive() -> bool:
    """Progress bars only for a person at a terminal: not in CI, not when stderr goes to a file or a pipe."""
    return sys.stderr.isatty() and not os.environ.get("CI")


def register_resolvers() -> None:
    OmegaConf.register_new_resolver("cb.fmt", format_value, replace=True)
    OmegaConf.register_new_resolver("cb.root", lambda: str(REPO_ROOT), replace=True)
    OmegaConf.register_new_resolver("cb.basename", lambda path: Path(str(path)).name, replace=True)
    OmegaConf.register_new_resolver("cb.recordings_key", recordings_key, replace=True)
    OmegaConf.register_new_resolver("cb.generations", generations, replace=True)
    OmegaConf.register_new_resolver("cb.interactive", interactive, replace=True)
    OmegaConf.register_new_resolver("cb.observed", observed, replace=True)
    OmegaConf.register_new_resolver("cb.wandb_offline", lambda: not os.environ.get("WANDB_API_KEY"), replace=True)


register_resolvers()
