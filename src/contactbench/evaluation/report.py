"""Collect every metrics.json under a folder into one results table (Markdown), and print where it is."""

from __future__ import annotations

import argparse
import html
import json
from pathlib import Path

from contactbench import atomic
from contactbench.errors import ContactbenchError
from contactbench.evaluation.figures import IMPORTANCE_THRESHOLD, SWEEPS, draw_all
from contactbench.evaluation.renders import render_report

COLUMNS = [
    ("model", "model", "{}"),
    ("dataset", "dataset", "{}"),
    ("variant", "variant", "{}"),
    ("split", "split", "{}"),
    ("n_trajectories", "tosses", "{}"),
    ("pos_err", "position error (widths)", "{:.4f}"),
    ("rot_err_rad", "rotation error (rad)", "{:.4f}"),
    ("floor_penetration_m", "floor penetration (mm)", "{:.2f}"),
    ("interbody_penetration_m", "inter-body penetration (mm)", "{:.2f}"),
    ("pairwise_collisions", "pairwise collisions", "{:.2f}"),
]
MILLIMETRES = {"floor_penetration_m", "interbody_penetration_m"}


def collect(root: Path) -> list[dict]:
    rows = []
    for path in sorted(Path(root).rglob("metrics.json")):
        row = json.loads(path.read_text())
        missing = [key for key, _, _ in COLUMNS if key not in row]
        if missing:
            raise ContactbenchError(
                f"{path}: field {missing[0]!r} missing (not a metrics.json written by evaluate.py/train.py)"
            )
        rows.append(row)
    return sorted(rows, key=lambda r: (r["dataset"], r["variant"], r["split"], r["model"]))


def _cell(row: dict, key: str, form: str) -> str:
    value = row.get(key)
    if value is None:
        return "–"
    return form.format(value * 1e3 if key in MILLIMETRES else value)


def markdown_table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(title for _, title, _ in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_cell(row, key, form) for key, _, form in COLUMNS) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def importance_markdown(table: dict[str, dict[str, str]]) -> str:
    dimensions = [parameter for parameter, _ in SWEEPS.values()]
    lines = ["| method | " + " | ".join(dimensions) + " |", "|" + "---|" * (len(dimensions) + 1)]
    lines += [
        f"| {model} | " + " | ".join(verdicts.get(d, "N/A") for d in dimensions) + " |"
        for model, verdicts in sorted(table.items())
    ]
    return "\n".join(lines) + "\n"


def write_report(root: Path, renders: bool = True) -> Path:
    """results.md and results.html in root: the results table, the paper's figures that the runs allow, Table 3, and
    (with renders) final poses of ground truth vs every method and a rollout GIF."""
    root = Path(root)
    rows = collect(root)
    if not rows:
        raise ContactbenchError(f"{root}: no metrics.json below it; run train.py or evaluate.py first")
    figures, importance = draw_all(root, root / "figures")
    rendered = render_report(root, root / "renders") if renders else []
    sections = [
        f"# Results under {root}\n\nEvery metrics.json below this folder ({len(rows)}); figures from the test split.\n",
        markdown_table(rows),
        "## Figures\n",
        *[f"![{path.stem}](figures/{path.name})\n" for path in figures],
        "## Table 3, recomputed\n",
        f"'Yes' when a method's mean test position error changes by more than {IMPORTANCE_THRESHOLD:.0%} of its "
        "smallest value across the dimension's variants; 'N/A' with fewer than two variants.\n",
        importance_markdown(importance),
        "## Renders (Figs. 4 and 6: final poses, ground truth grey; matplotlib, headless)\n",
        *[f"![{path.stem}](renders/{path.name})\n" for path in rendered],
    ]
    markdown = "\n".join(sections)
    atomic.write_text(root / "results.md", markdown)
    atomic.write_text(root / "results.html", _html(markdown))
    return root / "results.md"


def _html(markdown: str) -> str:
    """A plain HTML rendering of the report's Markdown (headings, tables, images, paragraphs)."""
    body, in_table = [], False
    for line in markdown.split("\n"):
        if line.startswith("|") and not in_table:
            body.append("<table border=1 cellspacing=0>")
            in_table = True
        elif not line.startswith("|") and in_table:
            body.append("</table>")
            in_table = False
        if line.startswith("|---"):
            continue
        if line.startswith("|"):
            body.append(
                "<tr>"
                + "".join(f"<td>{html.escape(cell.strip())}</td>" for cell in line.strip("|").split("|"))
                + "</tr>"
            )
        elif line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            body.append(f"<h{level}>{html.escape(line.lstrip('# '))}</h{level}>")
        elif line.startswith("!["):
            body.append(
                f'<p><img src="{html.escape(line[line.index("(") + 1 : line.index(")")])}" style="max-width:100%"></p>'
            )
        elif line.strip():
            body.append(f"<p>{html.escape(line)}</p>")
    if in_table:
        body.append("</table>")
    text = "\n".join(body)
    head = "<!doctype html>\n<html><head><meta charset='utf-8'><title>contactbench results</title></head><body>"
    return f"{head}\n{text}\n</body></html>\n"


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
