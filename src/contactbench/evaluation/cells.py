"""A cell of the results: one model's runs on one variant, split, budget and observation that differ only by seed,
with each metric's mean over the seeds and its 95% interval, and two cells' difference where they share tosses."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from contactbench.evaluation.intervals import Interval, of_cell, of_difference

# The metrics a cell reports (metrics.json's names and units; the tables show metres as mm).
METRICS = (
    "pos_err",
    "rot_err_rad",
    "floor_penetration_m",
    "floor_penetration_true_m",
    "interbody_penetration_m",
    "pairwise_collisions",
)


@dataclass
class Cell:
    model: str
    dataset: str
    variant: str
    split: str
    budget: str | None
    noise_mm: float
    frame_stride: int
    runs: dict = field(default_factory=dict)  # seed -> row (collect's, with its per-toss values in _tosses)
    # each metric's interval once: the grid, the sensitivity tables and the results file all ask for it
    _intervals: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def seeds(self) -> list:
        return sorted(self.runs, key=lambda seed: (seed is None, seed if seed is not None else 0))

    @property
    def n_trajectories(self) -> int:
        return int(next(iter(self.runs.values()))["n_trajectories"])

    @property
    def own_engine(self) -> bool:
        """Whether the model simulates with the engine that made the data (runs.py marks its metrics.json): its error
        says how well it recovers that engine's settings, not how good a contact model it is, so no ranking counts
        it."""
        return any(bool(row.get("own_engine")) for row in self.runs.values())

    def mean(self, metric: str) -> float | None:
        """The mean over seeds of each seed's mean over tosses; None where a run did not measure it."""
        values = [row.get(metric) for row in self.runs.values()]
        return None if any(value is None for value in values) else float(np.mean(values))

    def tosses(self, metric: str) -> list[np.ndarray] | None:
        """Each seed's per-toss values of a metric (None where a run wrote none)."""
        columns = [(row.get("_tosses") or {}).get(metric) for row in self.runs.values()]
        return None if any(column is None for column in columns) else columns

    def interval(self, metric: str) -> Interval | None:
        if metric not in self._intervals:
            measured = self.mean(metric) is not None
            values = [row[metric] for row in self.runs.values()] if measured else []
            self._intervals[metric] = of_cell(self.tosses(metric), values) if measured else None
        return self._intervals[metric]


def variant_order(variant: str) -> tuple:
    """A numbered variant (friction=0.25) by its number, before named ones, then by name."""
    try:
        return (0, float(variant.split("=", 1)[1]), variant)
    except (IndexError, ValueError):
        return (1, 0.0, variant)


def order(
    dataset: str, variant: str, budget: str | None, noise_mm: float, frame_stride: int, model: str, split: str
) -> tuple:
    """Where a cell goes in a table or a results file: by dataset, variant (variant_order), budget, noise, stride,
    model and split."""
    return (dataset, variant_order(variant), budget or "", float(noise_mm), int(frame_stride), model, split)


def cell_order(cell: Cell) -> tuple:
    return order(cell.dataset, cell.variant, cell.budget, cell.noise_mm, cell.frame_stride, cell.model, cell.split)


def cells_of(rows: list[dict]) -> list[Cell]:
    """Rows that differ only by seed, as one cell each (one row per seed: the last found for it), in a fixed order."""
    cells: dict[tuple, Cell] = {}
    for row in rows:
        key = (
            row["model"],
            row["dataset"],
            row["variant"],
            row["split"],
            row.get("budget"),
            float(row.get("noise_mm", 0.0)),
            int(row.get("frame_stride", 1)),
        )
        cells.setdefault(key, Cell(*key)).runs[row.get("seed")] = row
    return sorted(cells.values(), key=cell_order)


def same_tosses(a: Cell, b: Cell) -> bool:
    """Whether two cells were scored on the same tosses: the same data and split, as many tosses, and (where the runs
    wrote them) the same toss lengths."""
    if (a.dataset, a.variant, a.split, a.noise_mm, a.frame_stride) != (
        b.dataset,
        b.variant,
        b.split,
        b.noise_mm,
        b.frame_stride,
    ):
        return False
    rows = [*a.runs.values(), *b.runs.values()]
    if len({int(row["n_trajectories"]) for row in rows}) != 1:
        return False
    lengths = [(row.get("_tosses") or {}).get("length") for row in rows]
    known = [length for length in lengths if length is not None]
    return all(np.array_equal(known[0], length) for length in known[1:])


def difference(a: Cell, b: Cell, metric: str) -> Interval | None:
    """The 95% interval of a's mean minus b's (intervals.of_difference); None unless both measured it on the same
    tosses."""
    if not same_tosses(a, b) or a.mean(metric) is None or b.mean(metric) is None:
        return None
    means = [[row[metric] for row in cell.runs.values()] for cell in (a, b)]
    return of_difference(a.tosses(metric), b.tosses(metric), *means)


def not_significant(cells: dict[str, Cell], metric: str) -> tuple[list[tuple[str, str]], int]:
    """The pairs of models (in name order) whose difference in a metric has a 95% interval covering 0, and how many
    pairs could be compared at all."""
    pairs, compared = [], 0
    for left, right in itertools.combinations(sorted(cells), 2):
        interval = difference(cells[left], cells[right], metric)
        if interval is None:
            continue
        compared += 1
        if interval.covers(0.0):
            pairs.append((left, right))
    return pairs, compared
