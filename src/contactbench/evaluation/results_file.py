"""results/<budget>.csv: one row a cell (a model on a variant, split and observation, over its seeds), each metric
with its 95% interval, and the commit, date and wall time of the runs that made it.

A report writes the groups of cells its run tree scores (GROUP: one dataset variant, split and observation, whose
models are ranked against each other) and keeps the file's other groups as they were, each row with its own commit:
a sitting of some variants (make claims) adds them without erasing another sitting's (make headline), and a group
scored again is replaced whole."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from contactbench import atomic, provenance, variants
from contactbench.errors import ContactbenchError
from contactbench.evaluation.cells import METRICS, Cell, difference, order

UNKNOWN = "unknown"
# paper_variant: yes where conf/variant/ names the variant, no for a custom one (friction=0.3), empty for a recorded
# dataset (no variants)
KEYS = [
    "model",
    "dataset",
    "variant",
    "paper_variant",
    "split",
    "budget",
    "noise_mm",
    "frame_stride",
    "seeds",
    "tosses",
]
RECORDED = ["commit", "date", "wall_s"]
# "yes" where the model simulates with the engine that generated the data (Cell.own_engine: bullet_default on PyBullet's
# tosses), left out of its group's ranking (VERSUS_BEST: "own engine"). A file from before the column reads as "".
OWN_ENGINE = "own_engine"
OWN_ENGINE_RANK = "own engine"
# The most distinct body pairs any recorded test toss of the cell touched (Fig. 7b's claim is about a maximum, which
# no mean and interval can say); empty with one body.
PAIRS_MAX = "pairwise_collisions_true_max"
# Each cell against the lowest mean among the models scored on the same tosses: "best", "tie" where the paired 95%
# interval of the difference covers 0, "worse" where it does not; empty where no other model shares its tosses. A
# table written from this file alone can then say which differences are not significant.
RANKED = ("pos_err", "rot_err_rad")
VERSUS_BEST = tuple(f"{metric}_vs_best" for metric in RANKED)
HEADER = [
    *KEYS,
    OWN_ENGINE,
    *(f"{metric}{suffix}" for metric in METRICS for suffix in ("", "_low", "_high", "_interval")),
    PAIRS_MAX,
    *VERSUS_BEST,
    *RECORDED,
]


# The cells ranked against each other (versus_best; Cell attributes and row columns alike): a report replaces a group
# whole or leaves it as it was.
GROUP = ("dataset", "variant", "split", "budget", "noise_mm", "frame_stride")


def _number(value: float | None) -> str:
    # six significant digits: a last-bit difference between machines' sums does not change the file
    return "" if value is None else f"{value:.6g}"


def _recorded(row: dict, key: str):
    """What the run recorded about itself (provenance.json in its folder); None where it did not."""
    if row.get(key) is not None:
        return row[key]
    return provenance.read(row["_run"]).get(key) if row.get("_run") is not None else None


def _provenance(cell: Cell) -> dict[str, str]:
    """The cell's commits (each once), its latest date, and its runs' total wall time; 'unknown' where a run did
    not record it."""
    runs = [cell.runs[seed] for seed in cell.seeds]
    commits = [_recorded(row, "commit") for row in runs]
    dates = [_recorded(row, "date") for row in runs]
    walls = [_recorded(row, "wall_s") for row in runs]
    return {
        "commit": UNKNOWN if None in commits else " ".join(sorted({str(commit) for commit in commits})),
        "date": UNKNOWN if None in dates else max(str(date) for date in dates),
        "wall_s": UNKNOWN if None in walls else f"{sum(float(wall) for wall in walls):.1f}",
    }


def _most_pairs(cell: Cell) -> str:
    """The largest recorded pairwise-collision count over the cell's tosses and seeds; '' where none is known."""
    columns = cell.tosses("pairwise_collisions_true")
    values = np.concatenate([np.asarray(column, dtype=float) for column in columns]) if columns else np.array([])
    values = values[np.isfinite(values)]
    return f"{values.max():g}" if values.size else ""


def versus_best(cells: list[Cell]) -> list[dict[str, str]]:
    """Per cell (in order), its VERSUS_BEST columns among the cells scored on the same tosses; a cell of the data's
    own engine is ranked with none (OWN_ENGINE_RANK)."""
    ranks: list[dict[str, str]] = [
        dict.fromkeys(VERSUS_BEST, OWN_ENGINE_RANK if cell.own_engine else "") for cell in cells
    ]
    groups: dict[tuple, list[int]] = {}
    for index, cell in enumerate(cells):
        if cell.own_engine:
            continue
        groups.setdefault(tuple(getattr(cell, key) for key in GROUP), []).append(index)
    for members in groups.values():
        for metric, column in zip(RANKED, VERSUS_BEST):
            measured = [index for index in members if cells[index].mean(metric) is not None]
            if len(measured) < 2:
                continue
            best = min(measured, key=lambda index: (cells[index].mean(metric), cells[index].model))
            ranks[best][column] = "best"
            for index in measured:
                if index != best:
                    interval = difference(cells[index], cells[best], metric)
                    ranks[index][column] = "" if interval is None else "tie" if interval.covers(0.0) else "worse"
    return ranks


def row_of(cell: Cell, versus: dict[str, str] | None = None) -> dict[str, str]:
    row = {
        "model": cell.model,
        "dataset": cell.dataset,
        "variant": cell.variant,
        "paper_variant": {True: "yes", False: "no", None: ""}[variants.paper_variant(cell.dataset, cell.variant)],
        "split": cell.split,
        "budget": cell.budget or UNKNOWN,
        "noise_mm": f"{cell.noise_mm:g}",
        "frame_stride": str(cell.frame_stride),
        "seeds": " ".join(UNKNOWN if seed is None else str(seed) for seed in cell.seeds),
        "tosses": str(cell.n_trajectories),
        OWN_ENGINE: "yes" if cell.own_engine else "",
    }
    for metric in METRICS:
        interval = cell.interval(metric)
        row[metric] = _number(cell.mean(metric))
        row[f"{metric}_low"] = _number(None if interval is None else interval.low)
        row[f"{metric}_high"] = _number(None if interval is None else interval.high)
        row[f"{metric}_interval"] = "" if interval is None else interval.over
    row[PAIRS_MAX] = _most_pairs(cell)
    return {**row, **(versus or dict.fromkeys(VERSUS_BEST, "")), **_provenance(cell)}


def read_rows(path: Path) -> list[dict]:
    """A results file's rows; one line naming the file and what is wrong where it is not one."""
    try:
        with open(path, newline="") as handle:
            rows = list(csv.DictReader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise ContactbenchError(f"{path}: cannot be read as a results file ({error})") from None
    rows = [{OWN_ENGINE: "", **row} for row in rows]  # a file from before the column: no cell was marked
    missing = [key for key in HEADER if rows and key not in rows[0]]
    if not rows or missing:
        raise ContactbenchError(
            f"{path}: field {missing[0]!r} missing" if missing else f"{path}: no rows (expected a results file)"
        )
    return rows


def _row_order(row: dict[str, str]) -> tuple:
    """A written row's place: as its cell's (cells.order)."""
    keys = ("dataset", "variant", "budget", "noise_mm", "frame_stride", "model", "split")
    return order(*(row[key] for key in keys))


def merged(path: Path, rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """`rows` and the rows of the file at `path` (if any) in groups (GROUP) that `rows` do not score, in cell order."""
    scored = {tuple(row[key] for key in GROUP) for row in rows}
    kept = [row for row in read_rows(path) if tuple(row[key] for key in GROUP) not in scored] if path.exists() else []
    return sorted(kept + rows, key=_row_order)


def csv_text(rows: list[dict[str, str]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=HEADER, lineterminator="\n", extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def write_results(cells: list[Cell], folder: Path) -> list[Path]:
    """folder/<budget>.csv for every budget among the cells, its other groups kept (merged); the files written."""
    budgets = sorted({cell.budget or UNKNOWN for cell in cells})
    written = []
    for budget in budgets:
        path = Path(folder) / f"{budget}.csv"
        ranked = [cell for cell in cells if (cell.budget or UNKNOWN) == budget]
        rows = [row_of(cell, versus) for cell, versus in zip(ranked, versus_best(ranked))]
        atomic.write_text(path, csv_text(merged(path, rows)))
        written.append(path)
    return written
