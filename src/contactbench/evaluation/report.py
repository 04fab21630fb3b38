"""Collect every metrics.json under a folder into one results table (Markdown), and print where it is."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from contactbench import atomic
from contactbench.errors import ContactbenchError

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
            raise ContactbenchError(f"{path}: field {missing[0]!r} missing (not a metrics.json written by evaluate.py/train.py)")
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


def write_report(root: Path) -> Path:
    rows = collect(root)
    if not rows:
        raise ContactbenchError(f"{root}: no metrics.json below it; run train.py or evaluate.py first")
    path = Path(root) / "results.md"
    atomic.write_text(path, f"# Results under {root}\n\nEvery metrics.json below this folder ({len(rows)}).\n\n" + markdown_table(rows))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("root", type=Path, help="a run or multirun folder")
    try:
        path = write_report(parser.parse_args().root)
    except ContactbenchError as error:
        raise SystemExit(f"error: {error}") from None
    print(path.read_text())
    print(f"report: {path}")


if __name__ == "__main__":
    main()
