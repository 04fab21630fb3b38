"""The paper's findings side by side with ours: one row per finding (Figs. 1, 2, 3, 5, 7a, 7b and Table 3), the
paper's statement, our figure with its 95% interval, and a verdict, judged from results/<budget>.csv alone.

Only the test split's cells of the recordings as they are (no tracking noise, frame stride 1) and of the variants
the paper ran (conf/variant/) count. A claim needs every paper variant of its dataset for every model it names;
where the file lacks one, its row says "not run" and which cells are missing, never a figure from elsewhere.

How a row is judged, with the 95% intervals the file holds (a mean's interval over tosses, or seeds):
- one cell is above another when its interval lies wholly above the other's;
- a sweep is flat when its means change by at most IMPORTANCE_THRESHOLD of their smallest (Table 3's rule), or when
  every interval shares a common value; otherwise it rises (falls) when its last cell is above (below) its first,
  and is mixed when neither;
- reproduced: the paper's statement holds for every model it names; reversed: the opposite holds for every one (a
  rise read as a fall, the easiest case as the hardest); not reproduced: anything between.
"""

from __future__ import annotations

import argparse
import csv
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from contactbench import atomic
from contactbench.config import CONFIG_DIR
from contactbench.evaluation.figures import IMPORTANCE_THRESHOLD

REPRODUCED, NOT_REPRODUCED, REVERSED, NOT_RUN = "reproduced", "not reproduced", "reversed", "not run"
# The paper's three methods, by the model names of this benchmark.
LABELS = {"sysid": "SysID-MuJoCo", "gnn": "GNN", "hybrid": "Hybrid"}
# dataset -> its varied parameter (the variant's name is "<parameter>=<value>")
SWEEPS = {"bouncycubes": "restitution", "frictioncubes": "friction", "polyhedra": "faces", "multicubes": "bodies"}
MILLIMETRES = {"floor_penetration_m", "interbody_penetration_m"}
SHOWN_MISSING = 4  # groups of missing cells named in a "not run" row; the rest are counted


@dataclass(frozen=True)
class Value:
    """A cell's mean and its 95% interval (None without one: then the mean alone bounds it)."""

    mean: float
    low: float | None = None
    high: float | None = None

    @property
    def lower(self) -> float:
        return self.mean if self.low is None else self.low

    @property
    def upper(self) -> float:
        return self.mean if self.high is None else self.high

    def above(self, other: Value) -> bool:
        return self.lower > other.upper

    def shown(self, metric: str) -> str:
        scale = 1e3 if metric in MILLIMETRES else 1.0
        text = f"{self.mean * scale:.3g}"
        return text if self.low is None else f"{text} [{self.low * scale:.3g}–{self.high * scale:.3g}]"


@dataclass(frozen=True)
class Claim:
    finding: str
    paper: str
    ours: str
    verdict: str


class Results:
    """The test cells of results/<budget>.csv on the recordings as they are, by (model, dataset, variant)."""

    def __init__(self, rows: list[dict[str, str]]):
        self.rows = {
            (row["model"], row["dataset"], row["variant"]): row
            for row in rows
            if row.get("split") == "test"
            and _number(row.get("noise_mm")) == 0
            and _number(row.get("frame_stride")) == 1
        }

    @classmethod
    def read(cls, path: Path) -> Results:
        with open(path, newline="") as handle:
            return cls(list(csv.DictReader(handle)))

    def value(self, model: str, dataset: str, variant: str, metric: str) -> Value | None:
        row = self.rows.get((model, dataset, variant))
        mean = None if row is None else _number(row.get(metric))
        if mean is None:
            return None
        low, high = _number(row.get(f"{metric}_low")), _number(row.get(f"{metric}_high"))
        return Value(mean, low, high) if low is not None and high is not None else Value(mean)

    def models_on(self, dataset: str, variant: str) -> list[str]:
        return sorted(model for model, there, named in self.rows if (there, named) == (dataset, variant))


def _number(text: str | None) -> float | None:
    try:
        return float(text) if text not in (None, "") else None
    except ValueError:
        return None


def sweep(dataset: str) -> list[tuple[float, str]]:
    """The paper's variants of a dataset (conf/variant/<dataset>_<value>.yaml), as (value, variant name), in order."""
    parameter = SWEEPS[dataset]
    values = [path.stem[len(dataset) + 1 :] for path in (CONFIG_DIR / "variant").glob(f"{dataset}_*.yaml")]
    return sorted((float(value), f"{parameter}={value}") for value in values)


class Missing(Exception):
    """The cells a claim needs that the file lacks: (model, dataset, variant, metric) each."""

    def __init__(self, cells: list[tuple[str, str, str, str]]):
        super().__init__(describe_missing(cells))
        self.cells = cells


def describe_missing(cells: list[tuple[str, str, str, str]]) -> str:
    """'sysid bouncycubes pos_err at every paper variant; gnn multicubes ... at bodies=4, bodies=5'."""
    grouped: dict[tuple[str, str, str], list[str]] = {}
    for model, dataset, variant, metric in cells:
        grouped.setdefault((model, dataset, metric), []).append(variant)
    parts = []
    for (model, dataset, metric), names in grouped.items():
        every = dataset in SWEEPS and len(names) == len(sweep(dataset))
        parts.append(f"{model} {dataset} {metric} at " + ("every paper variant" if every else ", ".join(names)))
    shown = "; ".join(parts[:SHOWN_MISSING])
    return shown + (f"; and {len(parts) - SHOWN_MISSING} more" if len(parts) > SHOWN_MISSING else "")


def series(results: Results, models: list[str], dataset: str, metric: str, at=None) -> dict[str, list[Value]]:
    """Each model's values over the dataset's paper variants (those where at(value) holds); Missing if any lacks."""
    variants = [(value, name) for value, name in sweep(dataset) if at is None or at(value)]
    found, missing = {}, []
    for model in models:
        for _, name in variants:
            if results.value(model, dataset, name, metric) is None:
                missing.append((model, dataset, name, metric))
        found[model] = [results.value(model, dataset, name, metric) for _, name in variants]
    if missing:
        raise Missing(missing)
    return found


def trend(values: list[Value]) -> str:
    """flat, rises, falls or mixed (the module's rule)."""
    means = [value.mean for value in values]
    smallest = min(means)
    if max(means) - smallest <= IMPORTANCE_THRESHOLD * abs(smallest):
        return "flat"
    if max(value.lower for value in values) <= min(value.upper for value in values):
        return "flat"
    if values[-1].above(values[0]):
        return "rises"
    if values[0].above(values[-1]):
        return "falls"
    return "mixed"


def _ends(values: list[Value], dataset: str, metric: str, at=None) -> str:
    names = [name for value, name in sweep(dataset) if at is None or at(value)]
    return f"{values[0].shown(metric)} at {names[0]} → {values[-1].shown(metric)} at {names[-1]}"


def _verdict(holds: list[bool], opposite: list[bool]) -> str:
    return REPRODUCED if all(holds) else REVERSED if all(opposite) else NOT_REPRODUCED


def restitution(results: Results) -> tuple[str, str]:
    analytical, learned = ["sysid", "hybrid"], ["gnn"]
    found = series(results, analytical + learned, "bouncycubes", "pos_err")
    trends = {model: trend(values) for model, values in found.items()}
    ours = "; ".join(
        f"{model} {trends[model]}: {_ends(values, 'bouncycubes', 'pos_err')}" for model, values in found.items()
    )
    holds = [trends[m] == "rises" for m in analytical] + [trends[m] == "flat" for m in learned]
    # the opposite: the analytical models' error falls, or the roles swap (they stay flat while the GNN's rises)
    falls = all(trends[m] == "falls" for m in analytical)
    swapped = all(trends[m] == "flat" for m in analytical) and all(trends[m] == "rises" for m in learned)
    return "position error (widths): " + ours, _verdict(holds, [falls or swapped])


def friction(results: Results) -> tuple[str, str]:
    models = ["sysid", "gnn", "hybrid"]
    found = series(results, models, "frictioncubes", "pos_err")
    parts, holds, opposite = [], [], []
    for model, values in found.items():
        zero, rest = values[0], values[1:]
        easiest = all(other.above(zero) for other in rest)
        hardest = all(zero.above(other) for other in rest)
        rest_trend = trend(rest)
        holds.append(easiest and rest_trend in ("flat", "mixed"))
        opposite.append(hardest)
        where = "lowest" if easiest else "highest" if hardest else "not apart"
        span = f"{min(v.mean for v in rest):.3g}–{max(v.mean for v in rest):.3g}"
        parts.append(f"{model}: μ=0 {zero.shown('pos_err')} ({where}); μ>0 means {span}, {rest_trend}")
    return "position error (widths): " + "; ".join(parts), _verdict(holds, opposite)


def faces(results: Results) -> tuple[str, str]:
    models = ["sysid", "gnn"]
    found = series(results, models, "polyhedra", "rot_err_rad")
    parts, holds, opposite = [], [], []
    for model, values in found.items():
        upper = values[len(values) // 2 :]
        grows = all(value.above(values[0]) for value in upper)
        plateau = trend(upper) == "flat"
        holds.append(grows and plateau)
        opposite.append(values[0].above(values[-1]))
        shape = "grows, then plateaus" if grows and plateau else "grows, no plateau" if grows else trend(values)
        parts.append(f"{model} {shape}: {_ends(values, 'polyhedra', 'rot_err_rad')}")
    return "rotation error (rad): " + "; ".join(parts), _verdict(holds, opposite)


def bodies(results: Results) -> tuple[str, str]:
    models = ["sysid", "gnn"]
    parts, holds, opposite = [], [], []
    for metric, unit in (("pos_err", "position (widths)"), ("rot_err_rad", "rotation (rad)")):
        for model, values in series(results, models, "multicubes", metric).items():
            shape = trend(values)
            holds.append(shape == "rises")
            opposite.append(shape == "falls")
            ratio = f", ×{values[-1].mean / values[0].mean:.2g}" if values[0].mean > 0 else ""
            parts.append(f"{model} {unit} {shape}{ratio}: {_ends(values, 'multicubes', metric)}")
    return "; ".join(parts), _verdict(holds, opposite)


def several(value: float) -> bool:
    return value >= 2


def interbody(results: Results) -> tuple[str, str]:
    inter = series(results, ["gnn", "sysid"], "multicubes", "interbody_penetration_m", several)
    floor = series(results, ["gnn"], "multicubes", "floor_penetration_m", several)["gnn"]
    names = [name for value, name in sweep("multicubes") if several(value)]
    parts, holds, opposite = [], [], []
    for name, gnn, own_floor, sysid in zip(names, inter["gnn"], floor, inter["sysid"]):
        holds.append(gnn.above(own_floor) and gnn.above(sysid))
        opposite.append(sysid.above(gnn))
        parts.append(
            f"{name}: gnn {gnn.shown('interbody_penetration_m')} (its floor "
            f"{own_floor.shown('floor_penetration_m')}), sysid {sysid.shown('interbody_penetration_m')}"
        )
    return "inter-body penetration (mm): " + "; ".join(parts), _verdict(holds, opposite)


def pairwise(results: Results) -> tuple[str, str]:
    parts, holds, missing = [], [], []
    for bodies_count, name in [(value, name) for value, name in sweep("multicubes") if several(value)]:
        counts = [
            _number(results.rows[(model, "multicubes", name)].get("pairwise_collisions_true_max"))
            for model in results.models_on("multicubes", name)
        ]
        counts = [count for count in counts if count is not None]
        if not counts:
            missing.append(("any model", "multicubes", name, "pairwise_collisions_true_max"))
            continue
        most = max(counts)
        holds.append(most <= bodies_count)
        parts.append(f"K={bodies_count:g}: {most:g} (K(K-1)/2 = {bodies_count * (bodies_count - 1) / 2:g})")
    if missing:
        raise Missing(missing)
    return "most pairs one recorded test toss touched: " + "; ".join(parts), _verdict(holds, [False])


# Table 3 as printed: the dimensions that matter to each method (Hybrid's faces and bodies: N/A).
PAPER_TABLE3 = {
    "sysid": {"frictioncubes": "No", "bouncycubes": "Yes", "polyhedra": "Yes", "multicubes": "Yes"},
    "gnn": {"frictioncubes": "No", "bouncycubes": "Yes", "polyhedra": "Yes", "multicubes": "Yes"},
    "hybrid": {"frictioncubes": "Yes", "bouncycubes": "Yes"},
}


def matters(results: Results, model: str, dataset: str) -> str:
    """Table 3's entry from a sweep: Yes unless both the position and the rotation error are flat (the paper does not
    say which error its table weighs; its Fig. 1 text has the GNN's position flat and its rotation rising)."""
    shapes = [trend(series(results, [model], dataset, metric)[model]) for metric in ("pos_err", "rot_err_rad")]
    return "No" if shapes == ["flat", "flat"] else "Yes"


def table3(results: Results) -> tuple[str, str]:
    ours, missing, agree, disagree = {}, [], [], []
    for model, dimensions in PAPER_TABLE3.items():
        for dataset, printed in dimensions.items():
            try:
                found = matters(results, model, dataset)
            except Missing as gap:
                missing += gap.cells
                continue
            ours.setdefault(model, []).append(f"{SWEEPS[dataset]} {found}")
            (agree if found == printed else disagree).append(f"{model} {SWEEPS[dataset]}")
    if missing:
        raise Missing(missing)
    total = len(agree) + len(disagree)
    text = "; ".join(f"{model}: {', '.join(entries)}" for model, entries in ours.items())
    text += f" — {len(agree)} of {total} entries agree" + (f" (not: {', '.join(disagree)})" if disagree else "")
    return text, REPRODUCED if not disagree else REVERSED if not agree else NOT_REPRODUCED


FINDINGS: list[tuple[str, str, Callable[[Results], tuple[str, str]]]] = [
    (
        "Fig. 1 (restitution)",
        "The positional error steadily increases for the models with analytical components [SysID-MuJoCo, Hybrid], "
        "while staying fairly constant for GNN.",
        restitution,
    ),
    (
        "Fig. 2 (friction)",
        "μ = 0: all methods exhibit lower errors compared to higher μ; for μ > 0 we do not observe a trend.",
        friction,
    ),
    (
        "Fig. 3 (faces)",
        "Rotational error worsens as the number of faces increases, but plateaus [SysID-MuJoCo, GNN].",
        faces,
    ),
    (
        "Fig. 5 (bodies)",
        "A weak linear increase in positional and rotational errors as the number of bodies increases "
        "[SysID-MuJoCo, GNN].",
        bodies,
    ),
    (
        "Fig. 7a (inter-body penetration)",
        "GNN has significantly more inter-penetration between freely moving bodies compared to floor penetration; "
        "analytical methods' is bounded. Judged here: GNN's above its own floor penetration and above SysID-MuJoCo's.",
        interbody,
    ),
    (
        "Fig. 7b (pairwise collisions)",
        "The maximum number of pairwise collisions for a given K is K rather than K(K-1)/2.",
        pairwise,
    ),
    (
        "Table 3",
        "Important (Yes/No) — SysID-MuJoCo and GNN: friction No, restitution Yes, faces Yes, bodies Yes; Hybrid: "
        "friction Yes, restitution Yes (faces, bodies N/A). Judged here: Yes unless the position and the rotation "
        "error are both flat over the sweep.",
        table3,
    ),
]


def check(results: Results) -> list[Claim]:
    """Every finding judged from these results (a finding whose cells are missing: not run, and which)."""
    claims = []
    for finding, paper, judge in FINDINGS:
        try:
            ours, verdict = judge(results)
        except Missing as gap:
            ours, verdict = f"missing test cells: {gap}", NOT_RUN
        claims.append(Claim(finding, paper, ours, verdict))
    return claims


def markdown(claims: list[Claim], source: str) -> str:
    lines = [
        f"The paper's findings, judged from `{source}` (test split; a mean with its 95% interval [low–high]). "
        f"A sweep is flat when its means move by at most {IMPORTANCE_THRESHOLD:.0%} of the smallest or all intervals "
        "overlap; one cell is above another when their intervals do not overlap "
        "(contactbench/evaluation/claims.py).\n",
        "| finding | the paper | ours | verdict |",
        "|---|---|---|---|",
    ]
    lines += [f"| {c.finding} | {c.paper} | {c.ours} | **{c.verdict}** |" for c in claims]
    return "\n".join(lines) + "\n"


def claims_path(results_csv: Path) -> Path:
    """Where the table of a results file is written: results/<budget>_claims.md beside results/<budget>.csv."""
    return Path(results_csv).with_name(f"{Path(results_csv).stem}_claims.md")


def write_claims(results_csv: Path, source: str | None = None) -> tuple[Path, str]:
    """The table judged from one results file, written beside it; returns its path and Markdown."""
    text = markdown(check(Results.read(results_csv)), source or Path(results_csv).name)
    path = claims_path(results_csv)
    atomic.write_text(path, text)
    return path, text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path, help="a results/<budget>.csv the report wrote")
    arguments = parser.parse_args()
    print(markdown(check(Results.read(arguments.results)), str(arguments.results)))


if __name__ == "__main__":
    main()
