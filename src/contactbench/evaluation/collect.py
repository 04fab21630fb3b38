"""Every run below a folder: its metrics.json rows with their per-toss values, each score once, and what a sweep asked
for against what it wrote."""

from __future__ import annotations

import csv
import itertools
import json
import re
from pathlib import Path

import numpy as np
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Glob
from omegaconf import OmegaConf

from contactbench.config import CONFIG_DIR
from contactbench.errors import ContactbenchError
from contactbench.folders import OUTCOME, SIGNATURE

# What a metrics.json must hold to be a row of the report (older ones lack seed, budget and the recorded floor
# penetration: those are optional).
REQUIRED = (
    "model",
    "dataset",
    "variant",
    "split",
    "n_trajectories",
    "pos_err",
    "rot_err_rad",
    "floor_penetration_m",
    "interbody_penetration_m",
    "pairwise_collisions",
)


def read_per_trajectory(folder: Path) -> dict[str, np.ndarray] | None:
    """The per_trajectory.csv in folder as columns in toss order (an empty value is NaN); None without the file."""
    path = Path(folder) / "per_trajectory.csv"
    if not path.is_file():
        return None
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    if rows and "trajectory" in rows[0]:
        rows.sort(key=lambda row: int(float(row["trajectory"])))
    names = list(rows[0]) if rows else []
    return {name: np.array([float(row[name]) if row[name] else np.nan for row in rows]) for name in names}


def collect(root: Path) -> list[dict]:
    """Every metrics.json below root, each with its budget and the command and run folder that wrote it
    (source_run), its file (_path), run folder (_run) and per-toss values (_tosses, None without a
    per_trajectory.csv)."""
    rows = []
    for path in sorted(Path(root).rglob("metrics.json")):
        row = json.loads(path.read_text())
        missing = [key for key in REQUIRED if key not in row]
        if missing:
            raise ContactbenchError(
                f"{path}: field {missing[0]!r} missing (not a metrics.json written by evaluate.py/train.py)"
            )
        task, run_dir = _made_by(row, path)
        row["budget"] = row.get("budget") or _budget_of(run_dir, Path(root))
        row["source_run"] = f"{task}.py: {run_dir.relative_to(root).as_posix() if run_dir != Path(root) else '.'}"
        row["_task"], row["_path"], row["_run"] = task, path, run_dir
        row["_tosses"] = read_per_trajectory(path.parent)
        rows.append(row)
    return sorted(
        rows,
        key=lambda r: (r["dataset"], r["variant"], r["split"], r["model"], r["budget"] or "", r.get("seed") or 0),
    )


def _made_by(row: dict, path: Path) -> tuple[str, Path]:
    """The command that wrote a metrics.json and its run folder: train.py writes <run>/<split>/metrics.json beside
    the run's signature.json, evaluate.py <run>/metrics.json (older files do not say which)."""
    task = row.get("task")
    if task is None:
        in_split = path.parent.name in ("val", "test")
        task = "train" if in_split and (path.parent.parent / SIGNATURE).is_file() else "evaluate"
    return str(task), path.parent.parent if task == "train" else path.parent


def _budget_of(run_dir: Path, root: Path) -> str | None:
    """An older metrics.json's budget: from its folder's name (budget=quick), else its run's .hydra/config.yaml."""
    found = re.search(r"(?:^|[/,])budget=([\w-]+)", run_dir.relative_to(root).as_posix() if run_dir != root else "")
    if found:
        return found.group(1)
    record = run_dir / ".hydra" / "config.yaml"
    budget = OmegaConf.select(OmegaConf.load(record), "budget.name") if record.is_file() else None
    return None if budget is None else str(budget)


def _identity(row: dict) -> tuple:
    """What a row measures: two rows alike in all of it are the same score, written twice."""
    return (
        row["model"],
        row["dataset"],
        row["variant"],
        row["split"],
        row.get("budget"),
        row.get("seed"),
        row.get("noise_mm", 0.0),
        row.get("frame_stride", 1),
        row.get("context_frames"),
    )


def once_each(rows: list[dict]) -> tuple[list[dict], str]:
    """Each score once (train.py test=true and a later evaluate.py both score the same fitted model on test): the
    train.py row where there is one, else the first found; and a line naming what was left out ('' if nothing)."""
    chosen: dict[tuple, dict] = {}
    for row in rows:
        kept = chosen.setdefault(_identity(row), row)
        if kept["_task"] != "train" and row["_task"] == "train":
            chosen[_identity(row)] = row
    kept_rows = [row for row in rows if chosen[_identity(row)] is row]
    left = [row for row in rows if chosen[_identity(row)] is not row]
    if not left:
        return kept_rows, ""
    named = "; ".join(f"{row['source_run']} ({row['split']})" for row in left[:3])
    more = f"; and {len(left) - 3} more" if len(left) > 3 else ""
    return kept_rows, (
        f"Scored twice: {len(left)} row(s) repeat another's model, data, split, budget and seed and are shown once, "
        f"keeping the train.py row where there is one. Left out: {named}{more}.\n"
    )


def _same(a: str, b: str) -> bool:
    """Two override values alike as Hydra writes them into folder names (true / True, 0 / 0.0)."""
    try:
        return float(a) == float(b)
    except ValueError:
        return a.lower() == b.lower()


def _sweep_values(override) -> list[str]:
    value = override.value()
    if isinstance(value, Glob):
        return value.filter(sorted(path.stem for path in (CONFIG_DIR / override.key_or_group).glob("*.yaml")))
    return list(override.sweep_string_iterator())


def expected_cells(root: Path) -> list[dict] | None:
    """Every job the sweep under root was asked for (its multirun.yaml: the experiment's sweeper params and the command
    line's overrides) and what became of it: done (a metrics.json), skipped or failed (the job's outcome.json says
    why), unfinished (a folder without either), missing (no folder). None when root is not a sweep."""
    record = Path(root) / "multirun.yaml"
    if not record.is_file():
        return None
    hydra = OmegaConf.load(record).hydra
    lines = [f"{key}={value}" for key, value in (hydra.sweeper.params or {}).items()] + list(hydra.overrides.task)
    parsed = {override.key_or_group: override for override in OverridesParser.create().parse_overrides(lines)}
    sweeps = {key: _sweep_values(override) for key, override in parsed.items() if override.is_sweep_override()}
    folders = []
    for folder in sorted(path for path in Path(root).iterdir() if path.is_dir() and "=" in path.name):
        # Hydra's override_dirname: key=value items joined by ',' (a value may hold commas: {train:6,val:4})
        pairs = dict(item.partition("=")[::2] for item in re.split(r",(?=[\w.+/@-]+=)", folder.name))
        folders.append((pairs, folder))
    cells = []
    for values in itertools.product(*sweeps.values()):
        job = dict(zip(sweeps, values))
        match = next(
            (folder for pairs, folder in folders if all(_same(pairs.get(k, ""), v) for k, v in job.items())), None
        )
        status, why = "missing", "no job folder"
        if match is not None:
            outcome = match / OUTCOME
            if any(match.glob("*/metrics.json")) or (match / "metrics.json").is_file():
                status, why = "done", ""
            elif outcome.is_file():
                recorded = json.loads(outcome.read_text())
                status, why = str(recorded.get("status", "failed")), str(recorded.get("why", ""))
            else:
                status, why = "unfinished", f"no metrics.json yet: running, or stopped (see {match.name}/*.log)"
        cells.append({**job, "status": status, "why": why})
    return cells
