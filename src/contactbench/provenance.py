"""Where a run's scores come from: the code's commit, when the run finished and how long it took (provenance.json
in the run folder). Kept apart from metrics.json, whose bytes depend only on the code, the data and the seed."""

from __future__ import annotations

import json
import subprocess
import time
from datetime import datetime, timezone
from pathlib import Path

from contactbench import atomic
from contactbench.errors import ContactbenchError

FILE = "provenance.json"
FIELDS = ("commit", "date", "wall_s")
UNKNOWN = "unknown"
# The repository this package was imported from (src/contactbench/ -> the checkout's root).
_CHECKOUT = Path(__file__).resolve().parents[2]


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(
            ["git", "-C", str(_CHECKOUT), *args], capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def commit() -> str:
    """The checkout's commit, with '+modified' where tracked files differ from it (the scores may then come from code
    no commit holds); 'unknown' outside a git checkout."""
    head = _git("rev-parse", "HEAD")
    if not head:
        return UNKNOWN
    modified = _git("status", "--porcelain", "--untracked-files=no")
    return head + ("+modified" if modified else "")


class Stopwatch:
    """Started when a run starts; `write` records the provenance of what the run wrote into its folder."""

    def __init__(self) -> None:
        self.started = time.monotonic()

    def write(self, run_dir: Path) -> None:
        atomic.write_json(
            Path(run_dir) / FILE,
            {
                "commit": commit(),
                "date": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "wall_s": round(time.monotonic() - self.started, 1),
            },
        )


def read(run_dir: Path) -> dict:
    """A run folder's provenance (an empty dict where the run wrote none, e.g. an older run)."""
    path = Path(run_dir) / FILE
    if not path.is_file():
        return {}
    try:
        document = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ContactbenchError(f"{path}: not JSON ({error}); expected {{{', '.join(FIELDS)}}}") from None
    if not isinstance(document, dict):
        raise ContactbenchError(f"{path}: expected an object with {', '.join(FIELDS)}, got {type(document).__name__}")
    return {key: document[key] for key in FIELDS if key in document}
