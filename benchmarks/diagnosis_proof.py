"""The blind proof of diagnose.py: every library effect at two strengths, null datasets, and a non-cube shape.

Each case is generated with PyBullet (effects switched on there), copied with meta.generator stripped and a
neutral name, diagnosed through the same pipeline as `python diagnose.py` (quick budget unless --budget), and only
then scored against the hidden truth: named correctly, false alarms on nulls, fitted parameters vs the hidden ones,
and the fraction of the excess held-out error closed, (base - augmented) / (base - base on the same tosses generated
without the effect). Prints the confusion matrix and a table; writes proof.json and proof.md under --out.

    python benchmarks/diagnosis_proof.py                 # ~25 cases, about 30 min on 2 cores
    python benchmarks/diagnosis_proof.py --effects floor_tilt --strengths 2    # a subset
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from contactbench import atomic, runs
from contactbench.generation.effects import EFFECT_NAMES
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.recordings import read_recordings, write_recordings

ROOT = Path(__file__).resolve().parents[1]
CUBE = SceneSpec(name="frictioncubes", friction=0.5, restitution=0.0)
POLYHEDRON = SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=12)


def cases(effects: list[str], strengths: list[float]) -> list[dict]:
    """(shape, effect or None, strength, generation seed); nulls first, so every effect case finds its null."""
    listed = [
        {"shape": "cube", "effect": None, "strength": 0.0, "seed": 0},
        {"shape": "cube", "effect": None, "strength": 0.0, "seed": 1},
        {"shape": "dodecahedron", "effect": None, "strength": 0.0, "seed": 0},
    ]
    listed += [{"shape": "cube", "effect": e, "strength": s, "seed": 0} for e in effects for s in strengths]
    listed += [
        {"shape": "dodecahedron", "effect": e, "strength": 2.0, "seed": 0}
        for e in ("air_drag", "floor_tilt")
        if e in effects
    ]
    return listed


def case_name(case: dict) -> str:
    return f"{case['shape']}_seed{case['seed']}_" + (
        f"{case['effect']}_x{case['strength']:g}" if case["effect"] else "null"
    )


def blind_copy(case: dict, index: int, data_dir: Path) -> tuple[Path, list[dict]]:
    """Generate the case (kept if there), then a copy without meta.generator under a neutral name."""
    spec = CUBE if case["shape"] == "cube" else POLYHEDRON
    source = data_dir / "generated" / case_name(case)
    if not (source / "meta.json").exists():
        generate_dataset(
            spec,
            source,
            variant=case_name(case),
            seed=case["seed"],
            effects=(case["effect"],) if case["effect"] else (),
            effect_strength=case["strength"] or 1.0,
            progress=False,
        )
    full = read_recordings(source)
    hidden = full.meta["generator"]["effects"]
    blind = full.for_models(list(full.splits))
    blind.meta["name"] = f"blind-{index:02d}"
    target = data_dir / "blind" / f"blind-{index:02d}"
    write_recordings(target, blind)
    return target, hidden


def diagnose(path: Path, out_dir: Path, budget: str) -> dict:
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("diagnose", overrides=[f"recordings={path}", f"budget={budget}"])
    runs.diagnose(cfg, out_dir)
    return json.loads((out_dir / "diagnosis.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--effects", nargs="*", default=list(EFFECT_NAMES))
    parser.add_argument("--strengths", nargs="*", type=float, default=[1.0, 2.0])
    parser.add_argument("--budget", default="quick")
    parser.add_argument("--data", type=Path, default=ROOT / "data" / "proof")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "proof")
    args = parser.parse_args()
    started = time.perf_counter()
    rows, null_base = [], {}
    for index, case in enumerate(cases(args.effects, args.strengths)):
        path, hidden = blind_copy(case, index, args.data)
        case_started = time.perf_counter()
        document = diagnose(path, args.out / f"blind-{index:02d}", args.budget)
        named = [e["name"] for e in document["effects"]]
        base = document["heldout"]["base"]["pos_err"]
        augmented = document["heldout"]["augmented"]["pos_err"]
        if case["effect"] is None:
            null_base.setdefault((case["shape"], case["seed"]), base)
        reference = null_base.get((case["shape"], case["seed"]))
        excess = base - reference if reference is not None else float("nan")
        row = {
            **case,
            "name": case_name(case),
            "blind": path.name,
            "named": named,
            "verdict": document["verdict"],
            "correct": named == [case["effect"]] if case["effect"] else not named,
            "hidden": hidden[0]["parameters"] if hidden else {},
            "fitted": document["effects"][0]["parameters"] if document["effects"] else {},
            "base_pos_err": base,
            "augmented_pos_err": augmented,
            "null_base_pos_err": reference,
            "excess_closed": (base - augmented) / excess if case["effect"] and excess > 0 else None,
            "heldout_improvement": document["heldout"]["improvement"],
            "heldout_ci95": document["heldout"]["ci95"],
            "best_candidate": max(
                (c for c in document["candidates"] if c.get("val_improvement") is not None),
                key=lambda c: c["val_improvement"],
                default=None,
            ),
            "seconds": round(time.perf_counter() - case_started, 1),
        }
        rows.append(row)
        print(
            f"{row['name']:42s} -> {named or 'none'} {'OK' if row['correct'] else 'WRONG'}  base {base:.4f} aug "
            f"{augmented:.4f} "
            f"null {reference if reference is None else round(reference, 4)} closed {row['excess_closed']}  "
            f"({row['seconds']} s)",
            flush=True,
        )
    summary = summarise(rows, time.perf_counter() - started)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic.write_json(args.out / "proof.json", {"summary": summary, "cases": rows})
    atomic.write_text(args.out / "proof.md", summary["markdown"])
    print(summary["markdown"])


def summarise(rows: list[dict], seconds: float) -> dict:
    effect_rows = [r for r in rows if r["effect"]]
    null_rows = [r for r in rows if not r["effect"]]
    labels = sorted({r["effect"] for r in effect_rows}) + ["none"]
    predicted_labels = labels + sorted({n for r in rows for n in r["named"] if n not in labels}) + ["several"]
    matrix = {truth: {p: 0 for p in predicted_labels} for truth in labels}
    for r in rows:
        truth = r["effect"] or "none"
        predicted = "none" if not r["named"] else r["named"][0] if len(r["named"]) == 1 else "several"
        matrix[truth][predicted] += 1
    closed = [r["excess_closed"] for r in effect_rows if r["excess_closed"] is not None]
    named_rate = float(np.mean([r["correct"] for r in effect_rows])) if effect_rows else float("nan")
    false_alarms = sum(bool(r["named"]) for r in null_rows)
    lines = [
        f"# Diagnosis proof ({len(rows)} blind datasets, {seconds / 60:.1f} min)",
        "",
        f"- named correctly: {named_rate:.0%} of {len(effect_rows)} effect datasets (goal >= 90%)",
        f"- false alarms: {false_alarms} of {len(null_rows)} null datasets (goal 0)",
        f"- excess held-out error closed: median {np.median(closed):.0%}, mean {np.mean(closed):.0%} over "
        f"{len(closed)} (goal >= 50%)"
        if closed
        else "- excess closed: n/a",
        "",
        "## Confusion matrix (rows: hidden, columns: named)",
        "",
        "| hidden \\ named | " + " | ".join(predicted_labels) + " |",
        "|---|" + "---|" * len(predicted_labels),
        *[
            f"| {truth} | " + " | ".join(str(matrix[truth][p]) or "" for p in predicted_labels) + " |"
            for truth in labels
        ],
        "",
        "## Cases",
        "",
        "| dataset | named | base | augmented | base without effect | excess closed | hidden | fitted | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        closed_text = "–" if r["excess_closed"] is None else f"{r['excess_closed']:.0%}"
        lines.append(
            f"| {r['name']} | {', '.join(r['named']) or 'none'} | {r['base_pos_err']:.4f} | "
            f"{r['augmented_pos_err']:.4f} | "
            f"{'–' if r['null_base_pos_err'] is None else format(r['null_base_pos_err'], '.4f')} | {closed_text} | "
            f"{_short(r['hidden'])} | {_short(r['fitted'])} | {r['seconds']} |"
        )
    return {
        "named_correctly": named_rate,
        "false_alarms": false_alarms,
        "nulls": len(null_rows),
        "excess_closed_median": float(np.median(closed)) if closed else None,
        "excess_closed_mean": float(np.mean(closed)) if closed else None,
        "confusion": matrix,
        "seconds": seconds,
        "markdown": "\n".join(lines) + "\n",
    }


def _short(values: dict) -> str:
    return ", ".join(f"{k}={v:.3g}" for k, v in values.items())


if __name__ == "__main__":
    main()
