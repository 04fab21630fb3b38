"""OmegaConf resolvers the Hydra configs use: repository root and stable variant names."""

from __future__ import annotations

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


def interactive() -> bool:
    """Progress bars only for a person at a terminal: not in CI, not when stderr goes to a file or a pipe."""
    return sys.stderr.isatty() and not os.environ.get("CI")


def register_resolvers() -> None:
    OmegaConf.register_new_resolver("cb.fmt", format_value, replace=True)
    OmegaConf.register_new_resolver("cb.root", lambda: str(REPO_ROOT), replace=True)
    OmegaConf.register_new_resolver("cb.basename", lambda path: Path(str(path)).name, replace=True)
    OmegaConf.register_new_resolver("cb.generations", generations, replace=True)
    OmegaConf.register_new_resolver("cb.interactive", interactive, replace=True)
    OmegaConf.register_new_resolver("cb.observed", observed, replace=True)
    OmegaConf.register_new_resolver("cb.wandb_offline", lambda: not os.environ.get("WANDB_API_KEY"), replace=True)


register_resolvers()
