"""The blind proof of diagnose.py: library effects, effects outside the library, nulls, other shapes, no velocities.

A blind set is a YAML file in benchmarks/proof_sets/ (its cases are data, written and committed before the set is
run, and never tuned on afterwards). Its `generator` says who made the data:

- `library`: the project's own generator (generation.effects; `effects` switched on in PyBullet), the same
  parametrisation the diagnosis library was developed with (tuning, held_out ... held_out_15);
- `independent`: benchmarks/independent_generator.py, written without reading how the library models any effect
  (PyBullet's own friction features, per-step forces of other forms, floor tiles, a moving floor; plates and bricks).

Each case is generated (and its null twin: the same seed with the effect off), copied with meta.generator stripped
(and, for cases "without velocities", the recorded velocities too) under a neutral name, diagnosed through the same
pipeline as `python diagnose.py` (quick budget unless --budget), and only then scored against the hidden truth:

- a library effect: named, and nothing else (a different or an extra name is a wrong name), confirmed on test;
- an effect outside the library: verdict `unexplained`, located in a phase where that effect acts; a name is wrong;
- a null (or physics the base fits, `truth: base`): verdict `none` (a name or `unexplained` is a false alarm).

A case's size is the mean position change of the bodies' centres, in object widths, over the test tosses, against its
null twin. For named cases it also reports the fraction of the excess held-out error closed, (base - augmented) /
(base - base of the null twin). Prints the confusion matrix and a table; writes proof.json and proof.md under --out.

    python benchmarks/diagnosis_proof.py --set independent_1   # one set (16-23 cases, 7-50 min each on 2 cores)
    python benchmarks/diagnosis_proof.py --set held_out_15 --only floor_tilt
    python benchmarks/diagnosis_proof.py --set independent_5 --engines mujoco drake   # as if PyBullet did not exist
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import independent_generator  # beside this script (run as python benchmarks/diagnosis_proof.py)
import numpy as np
import yaml
from hydra import compose, initialize_config_dir

from contactbench import atomic, runs
from contactbench.generation.effects import OUTSIDE_LIBRARY
from contactbench.generation.generator import generate_dataset
from contactbench.generation.scenes import SceneSpec
from contactbench.metrics import position_error
from contactbench.recordings import read_recordings, write_recordings

ROOT = Path(__file__).resolve().parents[1]
SET_DIR = Path(__file__).resolve().parent / "proof_sets"
SETS = tuple(sorted(path.stem for path in SET_DIR.glob("*.yaml")))
SHAPES = {
    "cube": SceneSpec(name="frictioncubes", friction=0.5, restitution=0.0),
    "dodecahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=12),
    "octahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=8),
    "icosahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=20),
    "tetrahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=4),
    "truncated_octahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=14),
    "rhombicuboctahedron": SceneSpec(name="polyhedra", friction=0.5, restitution=0.125, faces=26),
}
# Where each of the library generator's outside effects acts: `unexplained` must locate the mismatch in one of these.
ACTS_IN = {
    "coriolis": ("free", "sliding", "rolling"),
    "floor_viscosity": ("sliding", "rolling"),
    "floor_centring": ("sliding", "rolling", "rest"),
    "spin_damping": ("free", "sliding", "rolling"),
}
NULL_TRUTHS = ("none", "base")  # nothing concealed, or physics the base simulator fits (a soft floor)
SIZE_THRESHOLD = 0.1  # widths: the effects the goal counts (issue: >= 90% of those right)


def read_set(name: str) -> list[dict]:
    """The cases of a blind set, each with its generator and its truth: `truth` (a list of library names, or one of
    NULL_TRUTHS, or "outside") and `acts_in` for an outside effect."""
    document = yaml.safe_load((SET_DIR / f"{name}.yaml").read_text())
    cases = []
    for index, listed in enumerate(document["cases"]):
        case = {**listed, "set": document["set"], "generator": document["generator"], "index": index}
        if document["generator"] == "library":
            effects = listed["effects"]
            outside = [e for e in effects if e in OUTSIDE_LIBRARY]
            case["truth"] = "outside" if outside else (effects or "none")
            if outside:
                case["acts_in"] = list(ACTS_IN[outside[0]])
            case["label"] = "+".join(effects) or "none"
        else:
            case["label"] = listed["effect"] or "none"
            if isinstance(case["truth"], str) and case["truth"] not in (*NULL_TRUTHS, "outside"):
                case["truth"] = [case["truth"]]
        cases.append(case)
    return cases


def case_name(case: dict) -> str:
    label = case["label"]
    strength = f"_x{case['strength']:g}" if label != "none" else ""
    return f"{case['shape']}_seed{case['seed']}_{label}{strength}" + ("" if case["velocities"] else "_novel")


def generate(case: dict, data_dir: Path, with_effect: bool) -> Path:
    """The case's dataset with its velocities (kept if there), or its null twin (the same seed, the effect off)."""
    if case["generator"] == "independent":
        return independent_generator.generate_case(
            {**case, "velocities": True}, data_dir / "independent", with_effect=with_effect
        )
    effects = tuple(case["effects"]) if with_effect else ()
    label = "+".join(effects) or "none"
    strength = f"_x{case['strength']:g}" if effects else ""
    target = data_dir / "generated" / f"{case['shape']}_seed{case['seed']}_{label}{strength}"
    if not (target / "meta.json").exists():
        generate_dataset(
            SHAPES[case["shape"]],
            target,
            variant=target.name,
            seed=case["seed"],
            effects=effects,
            effect_strength=case["strength"] or 1.0,
            progress=False,
        )
    return target


def size(with_effect: Path, without: Path) -> float:
    """Mean position change of the bodies' centres over the test tosses, in object widths."""
    moved, still = (read_recordings(path, ["test"]) for path in (with_effect, without))
    return float(np.nanmean(position_error(moved.split("test").poses, still.split("test").poses, moved.widths())))


def blind_copy(case: dict, data_dir: Path) -> tuple[Path, float]:
    """A copy without meta.generator (and without velocities where the case says so) under a neutral name, and the
    case's size."""
    source = generate(case, data_dir, with_effect=True)
    measured = 0.0 if case["label"] == "none" else size(source, generate(case, data_dir, with_effect=False))
    full = read_recordings(source)
    blind = full.for_models(list(full.splits))
    if not case["velocities"]:
        blind = dataclasses.replace(
            blind, splits={name: dataclasses.replace(split, velocities=None) for name, split in blind.splits.items()}
        )
    name = f"{case['set']}-{case['index']:02d}"
    blind.meta["name"] = name
    target = data_dir / "blind" / name
    write_recordings(target, blind)
    return target, measured


def unexplained_phase(document: dict) -> str | None:
    """The phase an `unexplained` verdict locates the mismatch in."""
    return (document.get("unexplained") or {}).get("phase")


def judge(case: dict, document: dict) -> dict:
    """Right, wrong name, false alarm, wrong place, unconfirmed or miss, against the hidden truth. A name counts only
    where the verdict is `effect` (confirmed on test); an unconfirmed candidate is no finding, right or wrong."""
    verdict, truth = document["verdict"], case["truth"]
    candidates = [e["name"] for e in document["effects"]]
    named = candidates if verdict == "effect" else []
    located = unexplained_phase(document)
    if truth in NULL_TRUTHS:
        outcome = {"none": "right", "unconfirmed": "unconfirmed"}.get(verdict, "false alarm")
    elif truth == "outside":
        if named:
            outcome = "wrong name"
        elif verdict == "unexplained":
            outcome = "right" if located in case["acts_in"] else "wrong place"
        else:
            outcome = "miss"
    elif any(name not in truth for name in named):
        outcome = "wrong name"
    elif named:
        outcome = "right" if sorted(named) == sorted(truth) else "miss"  # only one of two effects
    else:
        outcome = "unconfirmed" if sorted(candidates) == sorted(truth) else "miss"
    return {"named": named, "candidates": candidates, "verdict": verdict, "located": located, "outcome": outcome}


def diagnose(path: Path, out_dir: Path, budget: str, engines: list[str]) -> dict:
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        overrides = [f"recordings={path}", f"budget={budget}", f"engines=[{','.join(engines)}]"]
        cfg = compose("diagnose", overrides=overrides)
    runs.diagnose(cfg, out_dir)
    return json.loads((out_dir / "diagnosis.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", choices=SETS, required=True, help="the blind set (benchmarks/proof_sets/<set>.yaml)")
    parser.add_argument("--only", nargs="*", default=None, help="the cases with any of these labels (none: nulls)")
    parser.add_argument("--budget", default="quick")
    parser.add_argument(
        "--engines",
        nargs="+",
        default=["mujoco", "bullet", "drake"],
        help="the contact laws the diagnosis may choose its base from; leave out bullet to diagnose as if the "
        "generator's engine did not exist (the proof's second report)",
    )
    parser.add_argument(
        "--resume", action="store_true", help="keep the cases --out's proof.json holds already and run the others"
    )
    parser.add_argument("--data", type=Path, default=ROOT / "data" / "proof")
    parser.add_argument("--out", type=Path, default=None, help="default: outputs/proof/<set>")
    args = parser.parse_args()
    excluded = "" if "bullet" in args.engines else "_without_bullet"
    out = args.out or ROOT / "outputs" / "proof" / (args.set + excluded)
    started = time.perf_counter()
    rows = []
    if args.resume and (out / "proof.json").exists():
        rows = json.loads((out / "proof.json").read_text())["cases"]
    done = {row["name"] for row in rows}
    for listed in read_set(args.set):
        if args.only is not None and not set(args.only) & set(listed["label"].split("+")):
            continue
        if case_name(listed) in done:
            continue
        path, measured = blind_copy(listed, args.data)
        case_started = time.perf_counter()
        document = diagnose(path, out / path.name, args.budget, args.engines)
        held = document["heldout"]
        named = bool(document["effects"])  # on val, confirmed or not
        row = {
            **{k: v for k, v in listed.items() if k != "index"},
            "name": case_name(listed),
            "blind": path.name,
            "size_widths": measured,
            **judge(listed, document),
            "fitted": {e["name"]: e["parameters"] for e in document["effects"]},
            "base_pos_err": held["base"]["pos_err"],
            "augmented_pos_err": held["augmented"]["pos_err"],
            "heldout_improvement": held["improvement"] if named else None,
            "heldout_ci95": held["ci95"] if named else None,
            "predictor": _predictor_gain(document),
            "contact_law": document["contact_law"]["best"],
            "naming_base": document["naming_base"],
            "seconds": round(time.perf_counter() - case_started, 1),
        }
        rows.append(row)
        atomic.write_json(out / "proof.json", {"cases": rows})  # so far: a stopped run keeps what it diagnosed
        print(
            f"{row['name']:52s} size {measured:.3f} -> {row['verdict']} {row['named'] or ''} {row['located'] or ''} "
            f"{row['outcome'].upper()}  base {row['base_pos_err']:.4f} aug {row['augmented_pos_err']:.4f}  "
            f"({row['seconds']} s)",
            flush=True,
        )
    _excess_closed(rows)
    summary = summarise(args.set, rows, time.perf_counter() - started)
    out.mkdir(parents=True, exist_ok=True)
    atomic.write_json(out / "proof.json", {"summary": summary, "cases": rows})
    atomic.write_text(out / "proof.md", summary["markdown"])
    print(summary["markdown"])


def _predictor_gain(document: dict) -> float | None:
    """The flexible predictor's held-out gain over the fitted simulator, where the diagnosis ran it."""
    predictable = document.get("predictable") or {}
    return (predictable.get("test") or {}).get("gain")


def _excess_closed(rows: list[dict]) -> None:
    """(base - augmented) / (base - base of the null of the same shape and seed in the set), where one was run."""
    null_base = {(r["shape"], r["seed"]): r["base_pos_err"] for r in rows if r["label"] == "none"}
    for r in rows:
        reference = null_base.get((r["shape"], r["seed"]))
        excess = r["base_pos_err"] - reference if reference is not None else float("nan")
        r["null_base_pos_err"] = reference
        closed = r["base_pos_err"] - r["augmented_pos_err"]
        r["excess_closed"] = closed / excess if r["named"] and excess > 0 else None


def _predicted_label(row: dict) -> str:
    if row["verdict"] in ("none", "unexplained", "confounded", "unconfirmed"):
        return row["verdict"]
    return "+".join(sorted(row["named"]))


def _rate(rows: list[dict]) -> str:
    return f"{sum(r['outcome'] == 'right' for r in rows)} of {len(rows)}" if rows else "n/a"


def summarise(set_name: str, rows: list[dict], seconds: float) -> dict:
    effect_rows = [r for r in rows if r["truth"] not in NULL_TRUTHS]
    library_rows = [r for r in effect_rows if r["truth"] != "outside"]
    outside_rows = [r for r in effect_rows if r["truth"] == "outside"]
    sized = [r for r in effect_rows if r["size_widths"] >= SIZE_THRESHOLD]
    null_rows = [r for r in rows if r["truth"] in NULL_TRUTHS]
    truths = sorted({r["label"] for r in rows})
    special = ["unconfirmed", "unexplained", "confounded", "none"]
    predicted = sorted({_predicted_label(r) for r in rows} - set(special)) + special
    matrix = {truth: {label: 0 for label in predicted} for truth in truths}
    for r in rows:
        matrix[r["label"]][_predicted_label(r)] += 1
    closed = [r["excess_closed"] for r in library_rows if r["outcome"] == "right" and r["excess_closed"] is not None]
    wrong = [r["name"] for r in rows if r["outcome"] == "wrong name"]
    false_alarms = [r["name"] for r in null_rows if r["outcome"] == "false alarm"]
    worse = [r["name"] for r in rows if r["named"] and r["heldout_improvement"] <= 0]
    lines = [
        f"# Diagnosis proof, set {set_name} ({len(rows)} blind datasets, {seconds / 60:.1f} min, "
        f"{max((r['seconds'] for r in rows), default=0):.0f} s for the slowest)",
        "",
        f"- effects of size >= {SIZE_THRESHOLD} widths right (library: named and confirmed on test; outside: "
        f"`unexplained` in a phase where it acts): {_rate(sized)} (goal >= 90%)",
        f"- library effects named right and confirmed: {_rate(library_rows)}; outside the library `unexplained` in the "
        f"right phase: {_rate(outside_rows)}",
        f"- wrong names: {len(wrong)} (goal 0){': ' + ', '.join(wrong) if wrong else ''}",
        f"- false alarms: {len(false_alarms)} of {len(null_rows)} nulls (goal 0)"
        f"{': ' + ', '.join(false_alarms) if false_alarms else ''}",
        f"- named effects whose held-out full rollouts got worse: {len(worse)} (goal 0)"
        f"{': ' + ', '.join(worse) if worse else ''}",
        f"- excess held-out error closed where named right: median {np.median(closed):.0%} over {len(closed)}"
        if closed
        else "- excess closed: n/a",
        "",
        "## Confusion matrix (rows: hidden, columns: verdict)",
        "",
        "| hidden \\ verdict | " + " | ".join(predicted) + " |",
        "|---|" + "---|" * len(predicted),
        *[f"| {truth} | " + " | ".join(str(matrix[truth][p]) for p in predicted) + " |" for truth in truths],
        "",
        "## Cases",
        "",
        "| dataset | size (widths) | verdict | outcome | base | augmented | base of the null | excess closed | "
        "held-out full rollouts | predictor gain (test) | fitted | s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        verdict = ", ".join(r["named"]) or r["verdict"]
        if r["candidates"] and not r["named"]:
            verdict += f" (candidate {', '.join(r['candidates'])})"
        if r["verdict"] == "unexplained":
            verdict += f" ({r['located']})"
        lines.append(
            f"| {r['name']} | {r['size_widths']:.3f} | {verdict} | {r['outcome']} | {r['base_pos_err']:.4f} | "
            f"{r['augmented_pos_err']:.4f} | {_number(r['null_base_pos_err'], '.4f')} | "
            f"{_number(r['excess_closed'], '.0%')} | {_number(r['heldout_improvement'], '+.1%')} | "
            f"{_number(r['predictor'], '.1%')} | {_short(r['fitted'])} | {r['seconds']} |"
        )
    return {
        "sized_right": _rate(sized),
        "library_named_right": _rate(library_rows),
        "outside_unexplained_right": _rate(outside_rows),
        "wrong_names": wrong,
        "false_alarms": false_alarms,
        "nulls": len(null_rows),
        "named_worse_on_test": worse,
        "excess_closed_median": float(np.median(closed)) if closed else None,
        "confusion": matrix,
        "seconds": seconds,
        "markdown": "\n".join(lines) + "\n",
    }


def _number(value: float | None, spec: str) -> str:
    return "–" if value is None else format(value, spec)


def _short(values: dict) -> str:
    return "; ".join(
        f"{name}: " + ", ".join(f"{k}={v:.3g}" for k, v in parameters.items()) for name, parameters in values.items()
    )


if __name__ == "__main__":
    main()
