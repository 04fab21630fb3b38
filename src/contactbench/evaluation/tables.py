"""The report's tables in Markdown: every run, the model x variant grid, the sensitivity study, the sweep's jobs and
Table 3; every mean with its 95% interval, every row saying which models it cannot tell apart."""

from __future__ import annotations

from contactbench import variants
from contactbench.evaluation.cells import Cell, cells_of, not_significant, variant_order
from contactbench.evaluation.figures import (
    DIMENSIONS,
    IMPORTANCE_THRESHOLD,
    Run,
    importance_table,
    in_paper_figures,
    observed_plainly,
)
from contactbench.evaluation.intervals import LEVEL, RESAMPLES, over_tosses

COLUMNS = [
    ("model", "model", "{}"),
    ("dataset", "dataset", "{}"),
    ("variant", "variant", "{}"),
    ("split", "split", "{}"),
    ("seed", "seed", "{}"),
    ("n_trajectories", "tosses", "{}"),
    ("pos_err", "position error (widths)", "{:.4f}"),
    ("rot_err_rad", "rotation error (rad)", "{:.4f}"),
    ("floor_penetration_m", "floor penetration (mm)", "{:.2f}"),
    ("floor_penetration_true_m", "recorded floor penetration (mm)", "{:.2f}"),
    ("interbody_penetration_m", "inter-body penetration (mm)", "{:.2f}"),
    ("pairwise_collisions", "pairwise collisions", "{:.2f}"),
    ("budget", "budget", "{}"),
    ("source_run", "source run", "{}"),  # the command and run folder that wrote the row (collect adds it)
]
MILLIMETRES = {"floor_penetration_m", "floor_penetration_true_m", "interbody_penetration_m"}
# In the grid, beside a model whose test position error is not significantly different from the row's best.
NOT_SEPARABLE = "†"
# Beside a model scoring data its own engine made (Cell.own_engine), which no ranking of the row counts.
OWN_ENGINE = "‡"
# Beside an interval over the seeds' means (unmarked: over the test tosses).
OVER_SEEDS = "ˢ"
# The grid's and the sensitivity tables' metrics that each row compares between models, by their short names.
COMPARED = {"pos_err": "pos", "rot_err_rad": "rot"}


def mixed_budgets(rows: list[dict], where: str) -> str:
    """One warning line (and the blank line a table after it needs) when rows come from more than one budget."""
    counts: dict[str, int] = {}
    for row in rows:
        counts[row.get("budget") or "unknown"] = counts.get(row.get("budget") or "unknown", 0) + 1
    if len(counts) < 2:
        return ""
    listed = ", ".join(f"{budget} ({n})" for budget, n in sorted(counts.items()))
    return f"Warning: results of more than one budget in {where}: {listed}; compare within one budget only.\n\n"


def _with_interval(value: float, low: float | None, high: float | None, form: str, marked: bool = False) -> str:
    text = form.format(value)
    if low is None or high is None:
        return text
    return text + f" [{form.format(low)}–{form.format(high)}]" + (OVER_SEEDS if marked else "")


def _cell(row: dict, key: str, form: str) -> str:
    if key == "variant":
        return variants.label(row["dataset"], row["variant"])
    value = row.get(key)
    if value is None:
        return "–"
    if not isinstance(value, (int, float)) or key in ("seed", "n_trajectories"):
        return form.format(value)
    unit = 1e3 if key in MILLIMETRES else 1.0
    interval = over_tosses((row.get("_tosses") or {}).get(key, []))
    low, high = (None, None) if interval is None else (interval.low * unit, interval.high * unit)
    return _with_interval(value * unit, low, high, form)


def markdown_table(rows: list[dict]) -> str:
    """A row per run, each metric its mean over the run's test tosses and their bootstrap interval."""
    lines = ["| " + " | ".join(title for _, title, _ in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_cell(row, key, form) for key, _, form in COLUMNS) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _metric(cell: Cell, metric: str) -> str:
    mean, interval = cell.mean(metric), cell.interval(metric)
    if mean is None:
        return "–"
    if interval is None:
        return f"{mean:.3f}"
    return _with_interval(mean, interval.low, interval.high, "{:.3f}", marked=interval.over == "seeds")


def _seeds_cell(test: Cell | None, val: Cell | None = None) -> str:
    """Test position / rotation error with their intervals (– without a test run), val position error and, with
    several seeds, their number beside."""
    text = f"{_metric(test, 'pos_err')} / {_metric(test, 'rot_err_rad')}" if test else "–"
    beside = [f"val {val.mean('pos_err'):.3f}"] if val else []
    seeds = len((test or val).runs) if (test or val) else 0
    if seeds > 1:
        beside.append(f"n={seeds}")
    return text + (f" ({', '.join(beside)})" if beside else "")


def _ties(tests: dict[str, Cell]) -> tuple[str, set[frozenset]]:
    """A row's last column: per compared metric, the pairs of models it cannot tell apart ('none'; '–' with no two
    models on the same tosses); and the position pairs, for the mark beside the best."""
    parts, position = [], set()
    compared_any = False
    for metric, short in COMPARED.items():
        pairs, compared = not_significant(tests, metric)
        compared_any = compared_any or compared > 0
        if metric == "pos_err":
            position = {frozenset(pair) for pair in pairs}
        if pairs:
            parts.append(f"{short}: " + ", ".join(f"{a} ≈ {b}" for a, b in pairs))
    return ("; ".join(parts) or "none") if compared_any else "–", position


def intervals_note(rows: str = "row") -> str:
    return (
        f"\nEach error is a mean with its {LEVEL:.0%} interval [low–high]: with one seed, a percentile bootstrap over "
        f"the test tosses ({RESAMPLES} resamples, one fixed seed); with several seeds (n=…), the mean over seeds, and "
        "the wider of the Student-t interval over the seeds' means (marked "
        f"{OVER_SEEDS}) and the bootstrap over the tosses of the per-toss errors averaged over seeds. The last column "
        f"names the models of the {rows} whose difference in test position (pos) or rotation (rot) error is not "
        f"significant: its {LEVEL:.0%} interval covers 0 (a paired bootstrap over the same test tosses; with several "
        "seeds, the wider of that and Welch's t-interval over the seeds' means); 'none' when every pair differs, "
        "'–' when no two models were scored on the same tosses.\n"
    )


def grid_markdown(rows: list[dict]) -> str:
    """The model x dataset grid: test position / rotation error per variant and model with their intervals, val
    position beside. Runs that differ only by seed are one cell. In a row the lowest mean test position error is bold,
    NOT_SEPARABLE marks the models not significantly different from it, and the last column names every pair of
    models the row cannot tell apart."""
    cells = cells_of(rows)
    models = sorted({cell.model for cell in cells})
    grid: dict[tuple[str, str, str], dict[str, dict[str, Cell]]] = {}
    for cell in cells:
        at = (cell.dataset, cell.variant, cell.budget or "–")  # budgets never share a row
        grid.setdefault(at, {}).setdefault(cell.model, {})[cell.split] = cell
    lines = [
        "| dataset | variant | budget | " + " | ".join(models) + " | not significant (95%) |",
        "|---|---|---|" + "---|" * (len(models) + 1),
    ]
    order = lambda item: (item[0][0], variant_order(item[0][1]), item[0][2])  # noqa: E731
    for (dataset, variant, budget), by_model in sorted(grid.items(), key=order):
        tests = {
            model: splits["test"]
            for model, splits in by_model.items()
            if "test" in splits and not splits["test"].own_engine
        }
        best = min(tests, key=lambda model: tests[model].mean("pos_err")) if len(tests) > 1 else None
        ties, position = _ties(tests)
        entries = []
        for model in models:
            splits = by_model.get(model, {})
            text = _seeds_cell(splits.get("test"), splits.get("val"))
            if model == best:
                text = f"**{text}**"
            elif best is not None and frozenset((model, best)) in position:
                text += f" {NOT_SEPARABLE}"
            if "test" in splits and splits["test"].own_engine:
                text += f" {OWN_ENGINE}"
            entries.append(text)
        label = variants.label(dataset, variant)
        lines.append(f"| {dataset} | {label} | {budget} | " + " | ".join(entries) + f" | {ties} |")
    note = intervals_note() + (
        f"The lowest mean test position error of a row is in bold; {NOT_SEPARABLE} marks a model whose difference from "
        f"it is not significant; {OWN_ENGINE} marks a model that simulates with the engine that made the data (it "
        "recovers that engine's own settings, and no ranking counts it).\n"
    )
    return mixed_budgets(rows, "this table") + "\n".join(lines) + "\n" + note


def sensitivity_markdown(rows: list[dict]) -> str:
    """Test position / rotation error per model at every observation (noise, frame stride) that was run, per
    variant, with their intervals and which models each setting cannot tell apart, and one sentence per model and
    variant: how much its position error grew at the most noise and at the lowest frame rate against its plain run
    (means over seeds, as in the grid). Empty when every run observed the recordings as they are."""
    tests = [row for row in rows if row["split"] == "test"]
    if all(observed_plainly(row) for row in tests):
        return ""
    lines = list(filter(None, [mixed_budgets(tests, "this section")]))
    cells = cells_of(tests)
    several = len({cell.budget for cell in cells}) > 1
    for dataset, variant, budget in sorted(
        {(cell.dataset, cell.variant, cell.budget or "") for cell in cells},
        key=lambda key: (key[0], variant_order(key[1]), key[2]),
    ):
        here = (dataset, variant, budget)
        group = [cell for cell in cells if (cell.dataset, cell.variant, cell.budget or "") == here]
        settings = sorted({(cell.noise_mm, cell.frame_stride) for cell in group})
        models = sorted({cell.model for cell in group})
        scored = {run.get("scored_against", "recording") for cell in group for run in cell.runs.values()}
        at = {(cell.noise_mm, cell.frame_stride, cell.model): cell for cell in group}
        lines += [
            f"### {dataset} {variants.label(dataset, variant)} (test; scored against the {' / '.join(sorted(scored))}"
            + (f"; budget {budget or 'unknown'}" if several else "")
            + ")\n",
            "| noise (mm) | frame stride | " + " | ".join(models) + " | not significant (95%) |",
            "|---|---|" + "---|" * (len(models) + 1),
        ]
        for noise, stride in settings:
            entries = [_seeds_cell(at.get((noise, stride, model))) for model in models]
            ties, _ = _ties({model: at[(noise, stride, model)] for model in models if (noise, stride, model) in at})
            lines.append(f"| {noise:g} | {stride} | " + " | ".join(entries) + f" | {ties} |")
        lines.append("")
        for model in models:
            plain = at.get((0.0, 1, model))
            if plain is None:
                continue
            noisiest = max((s for s in settings if s[1] == 1 and (s[0], 1, model) in at), default=None)
            slowest = max((s for s in settings if s[0] == 0 and (0.0, s[1], model) in at), key=lambda s: s[1])
            parts = []
            if noisiest and noisiest[0] > 0:
                ratio = at[(noisiest[0], 1, model)].mean("pos_err") / plain.mean("pos_err")
                parts.append(f"{ratio:.2f}x its plain position error at {noisiest[0]:g} mm of noise")
            if slowest[1] > 1:
                ratio = at[(0.0, slowest[1], model)].mean("pos_err") / plain.mean("pos_err")
                parts.append(f"{ratio:.2f}x at 1/{slowest[1]} of the frame rate")
            if parts:
                lines.append(f"- {model}: " + "; ".join(parts) + ".")
        lines.append("")
    return "\n".join(lines) + intervals_note("setting") + "\n"


def expected_markdown(cells: list[dict]) -> str:
    statuses = ("done", "skipped", "failed", "unfinished", "missing")
    counts = {status: sum(cell["status"] == status for cell in cells) for status in statuses}
    lines = [f"{len(cells)} jobs asked for: " + ", ".join(f"{n} {status}" for status, n in counts.items()) + ".\n"]
    pending = [cell for cell in cells if cell["status"] != "done"]
    if pending:
        keys = [key for key in pending[0] if key not in ("status", "why")]
        lines += ["| " + " | ".join(keys) + " | status | why |", "|" + "---|" * (len(keys) + 2)]
        lines += ["| " + " | ".join(str(cell[key]) for key in [*keys, "status", "why"]) + " |" for cell in pending]
    return "\n".join(lines) + "\n"


def importance_sentence(seeded: bool) -> str:
    """Table 3's rule (figures.importance_table) in a sentence; the seeds' part only when some runs have several."""
    return (
        "'Yes' when a method's mean test position error"
        + (" (mean over seeds)" if seeded else "")
        + f" changes by more than {IMPORTANCE_THRESHOLD:.0%} of its smallest value across the dimension's variants"
        + (" and by more than the widest range (min–max) over seeds among those variants" if seeded else "")
        + "; 'N/A' with fewer than two variants.\n"
    )


def importance_markdown(table: dict[str, dict[str, str]]) -> str:
    """Table 3 over the dimensions that have at least two variants in these runs; says what the others need."""
    dimensions = list(DIMENSIONS.values())
    measured = [d for d in dimensions if any(verdicts.get(d, "N/A") != "N/A" for verdicts in table.values())]
    missing = [f"{dataset} ({parameter})" for dataset, parameter in DIMENSIONS.items() if parameter not in measured]
    note = (
        f"Not measured here (needs test runs on at least two variants of): {', '.join(missing)}.\n" if missing else ""
    )
    if not measured:
        return note
    lines = ["| method | " + " | ".join(measured) + " |", "|" + "---|" * (len(measured) + 1)]
    lines += [
        f"| {model} | " + " | ".join(verdicts.get(d, "N/A") for d in measured) + " |"
        for model, verdicts in sorted(table.items())
    ]
    return "\n".join(lines) + "\n\n" + note


def custom_variants(summaries: list[dict]) -> list[str]:
    """The variants among these runs that the benchmark does not name, each once and marked
    ('frictioncubes friction=0.3 (not a paper variant)')."""
    custom = {(row["dataset"], row["variant"]) for row in summaries if not in_paper_figures(row)}
    return [f"{dataset} {variants.label(dataset, variant)}" for dataset, variant in sorted(custom)]


def figures_left_out(summaries: list[dict]) -> str:
    """One line under the figures' heading naming the custom variants the paper's numbered figures leave out."""
    custom = custom_variants(summaries)
    if not custom:
        return ""
    return (
        "Left out of the paper's figures (Figs. 1, 2, 3, 5, 7): " + ", ".join(custom) + "; drawn, marked, in the "
        "error-over-time figures only.\n"
    )


def table3_markdown(runs: list[Run]) -> str:
    """Table 3 of the paper's variants only (a custom one is named, not counted); with several budgets, a method's
    row per budget, and a warning line."""
    custom = custom_variants([run.summary for run in runs])
    counted = [run for run in runs if in_paper_figures(run.summary)]
    warning = mixed_budgets([run.summary for run in counted], "Table 3")
    method = (lambda run: f"{run.summary['model']} ({run.summary['budget']})") if warning else None
    left_out = "Left out of Table 3: " + ", ".join(custom) + ".\n" if custom else ""
    return warning + importance_markdown(importance_table(counted, method)) + left_out
