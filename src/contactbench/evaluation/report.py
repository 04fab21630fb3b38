"""The report of every run below a folder: results.md and results.html (the tables, the paper's figures, Table 3,
the paper's findings judged one by one, renders), results/<budget>.csv, one row a cell with its 95% intervals, and
results/<budget>_claims.md, the findings' table judged from that file alone (claims.py)."""

from __future__ import annotations

import argparse
import base64
import html
import re
from pathlib import Path

from contactbench import atomic
from contactbench.errors import ContactbenchError
from contactbench.evaluation.cells import cells_of
from contactbench.evaluation.claims import write_claims
from contactbench.evaluation.collect import collect, expected_cells, once_each
from contactbench.evaluation.figures import draw_all, load_test_runs, observed_plainly
from contactbench.evaluation.renders import render_report
from contactbench.evaluation.results_file import write_results
from contactbench.evaluation.tables import (
    expected_markdown,
    figures_left_out,
    grid_markdown,
    importance_sentence,
    markdown_table,
    mixed_budgets,
    sensitivity_markdown,
    table3_markdown,
)


def write_report(root: Path, renders: bool = True, results: Path | None = None) -> Path:
    """results.md and results.html in root: the results table, the paper's figures that the runs allow, Table 3, and
    (with renders) final poses of ground truth vs every method and a rollout GIF; and <results>/<budget>.csv, one row
    a cell (results: root/results unless given)."""
    root = Path(root)
    results = root / "results" if results is None else Path(results)
    found = collect(root)
    if not found:
        raise ContactbenchError(f"{root}: no metrics.json below it; run train.py or evaluate.py first")
    every_row, repeats = once_each(found)
    rows = [row for row in every_row if observed_plainly(row)]
    seeded = len({row.get("seed") for row in rows if row["split"] == "test"}) > 1
    sensitivity = sensitivity_markdown(every_row)
    jobs = expected_cells(root)
    tests = {row["_path"]: row for row in every_row if row["split"] == "test"}
    test_runs = [run for run in load_test_runs(root) if run.path in tests]
    for run in test_runs:
        run.summary["budget"] = tests[run.path]["budget"]
    runs = [run for run in test_runs if observed_plainly(run.summary)]
    # First the results file, the step that reads a file already there: one it cannot merge with stops the report
    # before anything is written.
    written = write_results(cells_of(every_row), results)
    figures, _ = draw_all(root, root / "figures", test_runs)
    rendered = render_report(root, root / "renders") if renders else []
    files = ", ".join(f"`{_shown(path, root)}`" for path in written)
    claims = [write_claims(path) for path in written]
    sections = [
        f"# Results under {root}\n\nEvery metrics.json below this folder ({len(found)}); figures from the test "
        "split; tables and figures of the recordings as they are, except the sensitivity section. One row a cell "
        f"(a model on a variant, split and observation, over its seeds), with 95% intervals, commit, date and wall "
        f"time: {files}.\n",
        *([repeats] if repeats else []),
        *(
            ["## The jobs of the last sweep launched here (its multirun.yaml)\n", expected_markdown(jobs)]
            if jobs
            else []
        ),
        "## Test position error (widths) / rotation error (rad), val position error beside\n",
        grid_markdown(rows),
        "## Figures\n",
        *filter(None, [mixed_budgets([run.summary for run in runs], "the figures")]),
        *filter(None, [figures_left_out([run.summary for run in runs])]),
        *[f"![{path.stem}](figures/{path.name})\n" for path in figures],
        "## Table 3, recomputed\n",
        importance_sentence(seeded),
        table3_markdown(runs),
        "## The paper's findings, side by side\n",
        *[f"{text}\nAlso in `{_shown(path, root)}`.\n" for path, text in claims],
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
        "Each metric: the run's mean over the split's tosses and its 95% interval, a percentile bootstrap over them.\n",
        markdown_table(every_row),
    ]
    markdown = "\n".join(sections)
    atomic.write_text(root / "results.md", markdown)
    atomic.write_text(root / "results.html", _html(markdown, root))
    return root / "results.md"


def _shown(path: Path, root: Path) -> str:
    """A results file as the report names it: from the report's folder when inside it, else in full."""
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.resolve().as_posix()


STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1200px; margin: 2em auto; padding: 0 1em; color: #222; }
h1, h2 { border-bottom: 1px solid #ddd; padding-bottom: .2em; }
table { border-collapse: collapse; margin: 1em 0; font-size: 13px; }
th, td { border: 1px solid #ccc; padding: 4px 8px; text-align: right; white-space: nowrap; }
td:first-child, td:nth-child(2), th { text-align: left; }
td:last-child { white-space: normal; min-width: 16em; }
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
    parser.add_argument(
        "--results",
        type=Path,
        help="folder for <budget>.csv, one row a cell (default: <root>/results; `make matrix` names the "
        "repository's results/, the committed one)",
    )
    arguments = parser.parse_args()
    try:
        path = write_report(arguments.root, renders=not arguments.no_renders, results=arguments.results)
    except ContactbenchError as error:
        raise SystemExit(f"error: {error}") from None
    print(path.read_text())
    print(f"report: {path}")


if __name__ == "__main__":
    main()
