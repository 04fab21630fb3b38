"""Collect every metrics.json under a folder into one results table (Markdown), and print where it is."""

from __future__ import annotations

import argparse
import base64
import html
import itertools
import json
import re
from pathlib import Path

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Glob
from omegaconf import OmegaConf

from contactbench import atomic, variants
from contactbench.config import CONFIG_DIR
from contactbench.errors import ContactbenchError
from contactbench.evaluation.figures import (
    DIMENSIONS,
    IMPORTANCE_THRESHOLD,
    Run,
    Spread,
    draw_all,
    importance_table,
    load_test_runs,
    observed_plainly,
)
from contactbench.evaluation.renders import render_report
from contactbench.folders import OUTCOME, SIGNATURE

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
# Not in metrics.json written before they were recorded (a budget is then read from the run's folder or config).
OPTIONAL = {"seed", "floor_penetration_true_m", "budget", "source_run"}
# In the grid, beside a model that cannot be told from the row's best at these seeds.
NOT_SEPARABLE = "†"


def collect(root: Path) -> list[dict]:
    """Every metrics.json below root, each with its budget and the command and run folder that wrote it
    (source_run), and its file (_path)."""
    rows = []
    for path in sorted(Path(root).rglob("metrics.json")):
        row = json.loads(path.read_text())
        missing = [key for key, _, _ in COLUMNS if key not in row and key not in OPTIONAL]
        if missing:
            raise ContactbenchError(
                f"{path}: field {missing[0]!r} missing (not a metrics.json written by evaluate.py/train.py)"
            )
        task, run_dir = _made_by(row, path)
        row["budget"] = row.get("budget") or _budget_of(run_dir, Path(root))
        row["source_run"] = f"{task}.py: {run_dir.relative_to(root).as_posix() if run_dir != Path(root) else '.'}"
        row["_task"], row["_path"] = task, path
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


def mixed_budgets(rows: list[dict], where: str) -> str:
    """One warning line (and the blank line a table after it needs) when rows come from more than one budget."""
    counts: dict[str, int] = {}
    for row in rows:
        counts[row.get("budget") or "unknown"] = counts.get(row.get("budget") or "unknown", 0) + 1
    if len(counts) < 2:
        return ""
    listed = ", ".join(f"{budget} ({n})" for budget, n in sorted(counts.items()))
    return f"Warning: results of more than one budget in {where}: {listed}; compare within one budget only.\n\n"


def _cell(row: dict, key: str, form: str) -> str:
    if key == "variant":
        return variants.label(row["dataset"], row["variant"])
    value = row.get(key)
    if value is None:
        return "–"
    return form.format(value * 1e3 if key in MILLIMETRES else value)


def markdown_table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(title for _, title, _ in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_cell(row, key, form) for key, _, form in COLUMNS) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _over_seeds(by_seed: dict, key: str) -> str:
    """One run's value; over several seeds their mean and [min–max]."""
    spread = Spread.of([row[key] for row in by_seed.values()])
    return f"{spread.mean:.3f}" + (f" [{spread.low:.3f}–{spread.high:.3f}]" if spread.n > 1 else "")


def _mean(by_seed: dict, key: str) -> float:
    return Spread.of([row[key] for row in by_seed.values()]).mean


def _seeds_cell(test: dict, val: dict | None = None) -> str:
    """Test position / rotation error (– without a test run), val position error and, with several seeds, their
    number beside; test and val hold a cell's rows by seed."""
    text = f"{_over_seeds(test, 'pos_err')} / {_over_seeds(test, 'rot_err_rad')}" if test else "–"
    beside = [f"val {_mean(val, 'pos_err'):.3f}"] if val else []
    seeds = len(test) or len(val or {})
    if seeds > 1:
        beside.append(f"n={seeds}")
    return text + (f" ({', '.join(beside)})" if beside else "")


def grid_markdown(rows: list[dict]) -> str:
    """The model x dataset grid: test position / rotation error per variant and model, val position beside it. Runs
    that differ only by seed are one cell, their mean and [min–max]; in a row with several seeds the lowest mean test
    position error is bold and NOT_SEPARABLE marks the models whose seeds' range overlaps the best's."""
    models = sorted({row["model"] for row in rows})
    cells: dict[tuple[str, str, str], dict[str, dict[str, dict]]] = {}
    for row in rows:
        cell = (row["dataset"], row["variant"], row.get("budget") or "–")  # budgets never share a cell
        splits = cells.setdefault(cell, {}).setdefault(row["model"], {})
        splits.setdefault(row["split"], {})[row.get("seed")] = row  # one row per seed: the last found for it
    lines = [
        "| dataset | variant | budget | " + " | ".join(models) + " |",
        "|---|---|---|" + "---|" * len(models),
    ]
    seeded = False
    order = lambda item: (item[0][0], _variant_key(item[0][1]), item[0][2])  # noqa: E731
    for (dataset, variant, budget), by_model in sorted(cells.items(), key=order):
        tests = {
            model: Spread.of([row["pos_err"] for row in splits["test"].values()])
            for model, splits in by_model.items()
            if "test" in splits
        }
        best = min(tests, key=lambda model: tests[model].mean) if any(s.n > 1 for s in tests.values()) else None
        seeded = seeded or best is not None
        entries = []
        for model in models:
            splits = by_model.get(model, {})
            text = _seeds_cell(splits.get("test", {}), splits.get("val"))
            if model == best:
                text = f"**{text}**"
            elif best is not None and model in tests and tests[model].overlaps(tests[best]):
                text += f" {NOT_SEPARABLE}"
            entries.append(text)
        lines.append(f"| {dataset} | {variants.label(dataset, variant)} | {budget} | " + " | ".join(entries) + " |")
    note = (
        "\nOver several seeds a cell is their mean [min–max] (n seeds). In such a row the lowest mean test position "
        f"error is in bold, and {NOT_SEPARABLE} marks a model whose seeds' test position errors span a range that "
        "overlaps the best's: not separable from the best at these seeds.\n"
    )
    return mixed_budgets(rows, "this table") + "\n".join(lines) + "\n" + (note if seeded else "")


def sensitivity_markdown(rows: list[dict]) -> str:
    """Test position / rotation error per model at every observation (noise, frame stride) that was run, per
    variant, and one sentence per model and variant: how much its position error grew at the most noise and at the
    lowest frame rate against its plain run (means over seeds, as in the grid). Empty when every run observed the
    recordings as they are."""
    tests = [row for row in rows if row["split"] == "test"]
    if all(observed_plainly(row) for row in tests):
        return ""
    lines = list(filter(None, [mixed_budgets(tests, "this section")]))
    for dataset, variant in sorted({(row["dataset"], row["variant"]) for row in tests}):
        group = [row for row in tests if (row["dataset"], row["variant"]) == (dataset, variant)]
        settings = sorted({(row.get("noise_mm", 0.0), row.get("frame_stride", 1)) for row in group})
        models = sorted({row["model"] for row in group})
        against = " / ".join(sorted({row.get("scored_against", "recording") for row in group}))
        lines += [
            f"### {dataset} {variants.label(dataset, variant)} (test; scored against the {against})\n",
            "| noise (mm) | frame stride | " + " | ".join(models) + " |",
            "|---|---|" + "---|" * len(models),
        ]
        by_setting: dict[tuple, dict] = {}
        for row in group:
            setting = (row.get("noise_mm", 0.0), row.get("frame_stride", 1), row["model"])
            by_setting.setdefault(setting, {})[row.get("seed")] = row
        for noise, stride in settings:
            cells = [_seeds_cell(by_setting.get((noise, stride, model), {})) for model in models]
            lines.append(f"| {noise:g} | {stride} | " + " | ".join(cells) + " |")
        lines.append("")
        for model in models:
            plain = by_setting.get((0.0, 1, model))
            if plain is None:
                continue
            noisiest = max((s for s in settings if s[1] == 1 and (s[0], 1, model) in by_setting), default=None)
            slowest = max((s for s in settings if s[0] == 0 and (0.0, s[1], model) in by_setting), key=lambda s: s[1])
            parts = []
            if noisiest and noisiest[0] > 0:
                ratio = _mean(by_setting[(noisiest[0], 1, model)], "pos_err") / _mean(plain, "pos_err")
                parts.append(f"{ratio:.2f}x its plain position error at {noisiest[0]:g} mm of noise")
            if slowest[1] > 1:
                ratio = _mean(by_setting[(0.0, slowest[1], model)], "pos_err") / _mean(plain, "pos_err")
                parts.append(f"{ratio:.2f}x at 1/{slowest[1]} of the frame rate")
            if parts:
                lines.append(f"- {model}: " + "; ".join(parts) + ".")
        lines.append("")
    return "\n".join(lines) + "\n"


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


def _variant_key(variant: str) -> tuple:
    try:
        return (0, float(variant.split("=", 1)[1]))
    except (IndexError, ValueError):
        return (1, 0.0)


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


def table3_markdown(runs: list[Run]) -> str:
    """Table 3 of the paper's variants only (a custom one is named, not counted); with several budgets, a method's
    row per budget, and a warning line."""
    custom = sorted(
        {(run.summary["dataset"], run.summary["variant"]) for run in runs if not _counts_in_table3(run.summary)}
    )
    counted = [run for run in runs if _counts_in_table3(run.summary)]
    warning = mixed_budgets([run.summary for run in counted], "Table 3")
    method = (lambda run: f"{run.summary['model']} ({run.summary['budget']})") if warning else None
    left_out = (
        "Left out of Table 3: " + ", ".join(f"{dataset} {variants.label(dataset, v)}" for dataset, v in custom) + ".\n"
        if custom
        else ""
    )
    return warning + importance_markdown(importance_table(counted, method)) + left_out


def _counts_in_table3(summary: dict) -> bool:
    return variants.paper_variant(summary["dataset"], summary["variant"]) is not False


def write_report(root: Path, renders: bool = True) -> Path:
    """results.md and results.html in root: the results table, the paper's figures that the runs allow, Table 3, and
    (with renders) final poses of ground truth vs every method and a rollout GIF."""
    root = Path(root)
    found = collect(root)
    if not found:
        raise ContactbenchError(f"{root}: no metrics.json below it; run train.py or evaluate.py first")
    every_row, repeats = once_each(found)
    rows = [row for row in every_row if observed_plainly(row)]
    seeded = len({row.get("seed") for row in rows if row["split"] == "test"}) > 1
    sensitivity = sensitivity_markdown(every_row)
    cells = expected_cells(root)
    tests = {row["_path"]: row for row in every_row if row["split"] == "test"}
    test_runs = [run for run in load_test_runs(root) if run.path in tests]
    for run in test_runs:
        run.summary["budget"] = tests[run.path]["budget"]
    runs = [run for run in test_runs if observed_plainly(run.summary)]
    figures, _ = draw_all(root, root / "figures", test_runs)
    rendered = render_report(root, root / "renders") if renders else []
    sections = [
        f"# Results under {root}\n\nEvery metrics.json below this folder ({len(found)}); figures from the test "
        "split; tables and figures of the recordings as they are, except the sensitivity section.\n",
        *([repeats] if repeats else []),
        *(
            ["## The jobs of the last sweep launched here (its multirun.yaml)\n", expected_markdown(cells)]
            if cells
            else []
        ),
        "## Test position error (widths) / rotation error (rad), val position error beside\n",
        grid_markdown(rows),
        "## Figures\n",
        *filter(None, [mixed_budgets([run.summary for run in runs], "the figures")]),
        *[f"![{path.stem}](figures/{path.name})\n" for path in figures],
        "## Table 3, recomputed\n",
        importance_sentence(seeded),
        table3_markdown(runs),
        "## Renders (Figs. 4 and 6: final poses, ground truth grey; matplotlib, headless)\n",
        *[f"![{path.stem}](renders/{path.name})\n" for path in rendered],
        *(
            [
                "## Sensitivity to tracking noise and frame rate (test position / rotation error)\n",
                "Every observation that was run (`observation.noise_mm`, `observation.frame_stride`); the figures "
                "above named sensitivity_* draw the same runs with their 25-75% bands. At a frame stride n the "
                "context frames span n times as long, so the predicted part of a toss starts later and is shorter: "
                "errors across strides are not over the same stretch of time.\n",
                sensitivity,
            ]
            if sensitivity
            else []
        ),
        "## Every run\n",
        markdown_table(every_row),
    ]
    markdown = "\n".join(sections)
    atomic.write_text(root / "results.md", markdown)
    atomic.write_text(root / "results.html", _html(markdown, root))
    return root / "results.md"


STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1200px; margin: 2em auto; padding: 0 1em; color: #222; }
h1, h2 { border-bottom: 1px solid #ddd; padding-bottom: .2em; }
table { border-collapse: collapse; margin: 1em 0; font-size: 13px; }
th, td { border: 1px solid #ccc; padding: 4px 8px; text-align: right; white-space: nowrap; }
td:first-child, td:nth-child(2), th { text-align: left; }
tr:first-child td { background: #f0f0f0; font-weight: 600; }
tr:nth-child(even) td { background: #fafafa; }
img { max-width: 100%; border: 1px solid #eee; margin: .5em 0; }
"""


def _html(markdown: str, root: Path) -> str:
    """One self-contained, styled HTML file of the report's Markdown: images embedded as data URIs."""
    body, in_table = [], False
    for line in markdown.split("\n"):
        if line.startswith("|") and not in_table:
            body.append("<table>")
            in_table = True
        elif not line.startswith("|") and in_table:
            body.append("</table>")
            in_table = False
        if line.startswith("|---"):
            continue
        if line.startswith("|"):
            cells = [
                re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", html.escape(cell.strip())) for cell in line.strip("|").split("|")
            ]
            body.append("<tr>" + "".join(f"<td>{cell}</td>" for cell in cells) + "</tr>")
        elif line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            body.append(f"<h{level}>{html.escape(line.lstrip('# '))}</h{level}>")
        elif line.startswith("!["):
            body.append(f'<p><img src="{_embedded(root / line[line.index("(") + 1 : line.index(")")])}"></p>')
        elif line.strip():
            body.append(f"<p>{html.escape(line)}</p>")
    if in_table:
        body.append("</table>")
    text = "\n".join(body)
    head = (
        "<!doctype html>\n<html><head><meta charset='utf-8'><title>contactbench results</title>"
        f"<style>{STYLE}</style></head><body>"
    )
    return f"{head}\n{text}\n</body></html>\n"


def _embedded(path: Path) -> str:
    kind = {".png": "image/png", ".gif": "image/gif", ".svg": "image/svg+xml"}.get(path.suffix, "image/png")
    return f"data:{kind};base64,{base64.b64encode(path.read_bytes()).decode('ascii')}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("root", type=Path, help="a run or multirun folder")
    parser.add_argument("--no-renders", action="store_true", help="skip re-rolling models for the renders")
    arguments = parser.parse_args()
    try:
        path = write_report(arguments.root, renders=not arguments.no_renders)
    except ContactbenchError as error:
        raise SystemExit(f"error: {error}") from None
    print(path.read_text())
    print(f"report: {path}")


if __name__ == "__main__":
    main()
