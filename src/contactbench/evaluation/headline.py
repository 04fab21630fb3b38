"""The README's headline table, written from the committed results file alone (results/<budget>.csv): every model on
the real datasets, test position and rotation error with their 95% intervals, the best bold and the models not
significantly different from it marked. The README holds it between two markers; this rewrites what lies between.

    python -m contactbench.evaluation.headline            # README.md from results/quick.csv
    python -m contactbench.evaluation.headline --check    # exit 1 if README.md's table is not the file's
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from contactbench import atomic
from contactbench.config import REPO_ROOT
from contactbench.errors import ContactbenchError
from contactbench.evaluation.results_file import UNKNOWN, read_rows

RESULTS = REPO_ROOT / "results" / "quick.csv"
README = REPO_ROOT / "README.md"
BEGIN = "<!-- headline: python -m contactbench.evaluation.headline writes this from results/quick.csv -->"
END = "<!-- /headline -->"
# The real datasets (dataset, variant) and their columns' names.
REAL = {("contactnets_cube", "real"): "real cube", ("contactnets_elbow", "real"): "real elbow"}
# The order of the rows; a model the file holds beyond these follows them in name order.
ORDER = (
    "mujoco_default",
    "mujoco_fixed_acosta2022",
    "sysid",
    "sysid_mjx",
    "mujoco_sysid",
    "bullet_default",
    "sysid_bullet",
    "drake_default",
    "sysid_drake",
    "gnn",
    "gnn_paper",
    "hybrid",
    "residual",
)
TIE = "≈"
METRICS = {"pos_err": "{:.3f}", "rot_err_rad": "{:.2f}"}


def _cell(row: dict | None, metric: str) -> str:
    if row is None or not row[metric]:
        return "–"
    text, low, high = (METRICS[metric].format(float(row[f"{metric}{suffix}"])) for suffix in ("", "_low", "_high"))
    rank = row.get(f"{metric}_vs_best", "")
    mean = f"**{text}**" if rank == "best" else f"{text} {TIE}" if rank == "tie" else text
    return f"{mean} [{low}–{high}]"


def table(rows: list[dict]) -> str:
    """The markdown between the markers: the table and where its numbers come from."""
    test = {
        (row["model"], (row["dataset"], row["variant"])): row
        for row in rows
        if row["split"] == "test" and (row["dataset"], row["variant"]) in REAL and float(row["noise_mm"] or 0) == 0
    }
    if not test:
        raise ContactbenchError("the results file holds no test row of the real datasets (contactnets_cube/_elbow)")
    present = {model for model, _ in test}
    models = [m for m in ORDER if m in present] + sorted(present - set(ORDER))
    header = " | ".join(f"{name}: position (widths) | {name}: rotation (rad)" for name in REAL.values())
    lines = [f"| model | {header} |", "|---" * (1 + 2 * len(REAL)) + "|"]
    for model in models:
        cells = [_cell(test.get((model, dataset)), metric) for dataset in REAL for metric in METRICS]
        lines.append(f"| `{model}` | " + " | ".join(cells) + " |")
    used = list(test.values())
    commits = sorted({row["commit"] for row in used})
    dates = sorted({row["date"][:10] for row in used if row["date"] != UNKNOWN})
    seeds = sorted({row["seeds"] for row in used})
    budgets = sorted({row["budget"] for row in used})
    walls = [float(row["wall_s"]) for row in used if row["wall_s"] not in ("", UNKNOWN)]
    lines += [
        "",
        f"Test split; budget {', '.join(budgets)}; seed(s) {', '.join(seeds)}; each error the mean over the test "
        "tosses with its 95% interval [low–high] (bootstrap over tosses; over seeds too where several ran). "
        f"**Bold**: the lowest mean of its column; {TIE}: not significantly different from it (paired bootstrap "
        "over the same tosses); –: no such run (the model refuses the dataset, with one line saying why). From "
        f"`results/quick.csv`: commit {', '.join(c[:12] for c in commits)}; "
        f"{' to '.join(dict.fromkeys([dates[0], dates[-1]])) if dates else 'dates unknown'}; "
        f"{sum(walls) / 60:.0f} min of runs in all.",
    ]
    return "\n".join(lines)


def rewritten(readme_text: str, rows: list[dict], where: Path = README) -> str:
    """The README with the text between the markers replaced by table(rows)."""
    if readme_text.count(BEGIN) != 1 or readme_text.count(END) != 1:
        raise ContactbenchError(f"{where}: expected the markers {BEGIN!r} and {END!r} once each")
    before, rest = readme_text.split(BEGIN)
    _, after = rest.split(END)
    return f"{before}{BEGIN}\n{table(rows)}\n{END}{after}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--readme", type=Path, default=README)
    parser.add_argument("--check", action="store_true", help="exit 1 if the README's table is not the file's")
    args = parser.parse_args(argv)
    try:
        text = args.readme.read_text()
        new = rewritten(text, read_rows(args.results), args.readme)
    except ContactbenchError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.check:
        if new != text:
            print(
                f"{args.readme}: the headline is not the one {args.results} gives; run without --check", file=sys.stderr
            )
            return 1
        return 0
    if new != text:
        atomic.write_text(args.readme, new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
