"""Calibrate diagnosis.predictable on null datasets, for every base the diagnosis can name on, and show that it
detects concealed effects.

Generates (once) null datasets (nothing concealed) and datasets with one concealed effect, fits each base simulator on
each at the quick budget as the diagnosis fits it (the diagnosis' own MuJoCo base; with --engines, every contact option
of those engines too: their law searched as diagnosis.contact_law searches it, then refitted as the pipeline refits
the base it names on), runs predictable.check on each base and prints one line and one table row per dataset and base:
each statistic's val and test gain with the lower ends of their 95% intervals, which pass their null bounds, where and
on what, and whether the open-world correction (diagnosis.open_world) passes. Fits are cached as JSON under
data/predictable/cache/ (refitted when a base's parameters change). After a run it prints, per base, the bounds the
nulls of the calibration sets give (largest upper interval end + predictable.NULL_MARGIN): the values of
predictable.NULL_GAIN_BOUNDS. Records are kept in data/predictable/results_<set>.json (git-ignored, as all of data/).

The sets: `calibration` (the project's own generator: the nulls that set the bounds, and effects), `independent_nulls`
(nulls of benchmarks/independent_generator.py at seeds no blind set uses: PyBullet stepped and materialled otherwise,
so that no base matches them exactly, as none matches a blind set or real recordings), and the held-out sets, run
once each after the bounds they test were set.

    python benchmarks/predictable_calibration.py                    # the calibration set, MuJoCo base
    python benchmarks/predictable_calibration.py --set independent_nulls --engines mujoco bullet drake
    python benchmarks/predictable_calibration.py --set held_out     # other seeds, shapes and strengths
    python benchmarks/predictable_calibration.py --only cube_seed0  # the cases whose name contains it
    python benchmarks/predictable_calibration.py --fit-only         # generate and fit, no check
"""

from __future__ import annotations

import argparse
import fcntl
import json
import math
import time
from pathlib import Path

import independent_generator  # beside this script
import numpy as np
import torch
from diagnosis_proof import SHAPES  # beside this script: the proof's shapes, at the same nominal contact

from contactbench import atomic
from contactbench.diagnosis import contact_law, open_world, predictable
from contactbench.diagnosis.bases import engine_bases
from contactbench.diagnosis.library import Hypothesis
from contactbench.diagnosis.state import Budget, Diagnosis
from contactbench.generation.generator import generate_dataset
from contactbench.recordings import read_recordings
from contactbench.sim.engines import engine

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "predictable"
NULLS = (
    *(("cube", seed, (), 1.0) for seed in range(5)),
    *((shape, seed, (), 1.0) for shape in ("dodecahedron", "octahedron", "tetrahedron") for seed in (0, 1)),
    *((shape, 0, (), 1.0) for shape in ("icosahedron", "truncated_octahedron")),
)
OUTSIDE = ("floor_viscosity", "spin_damping", "coriolis", "floor_centring")
EFFECTS = (
    *(("cube", 0, (effect,), 1.0) for effect in (*OUTSIDE, "anisotropic_friction", "wind")),
    *(("cube", 0, (effect,), 2.0) for effect in ("floor_viscosity", "spin_damping", "anisotropic_friction")),
    *(("dodecahedron", 2, (effect,), 1.0) for effect in ("floor_viscosity", "coriolis", "floor_centring", "wind")),
)
# Run once, after NULL_GAIN_BOUNDS was set from the sets above: other seeds, shapes and strengths.
HELD_OUT_NULLS = (
    *(("cube", seed, (), 1.0) for seed in (5, 6)),
    ("dodecahedron", 3, (), 1.0),
    ("octahedron", 2, (), 1.0),
    ("tetrahedron", 2, (), 1.0),
    ("icosahedron", 1, (), 1.0),
    ("truncated_octahedron", 1, (), 1.0),
    ("rhombicuboctahedron", 0, (), 1.0),
)
HELD_OUT_EFFECTS = (
    *(("cube", 1, (effect,), 1.5) for effect in (*OUTSIDE, "anisotropic_friction", "wind")),
    *(("octahedron", 3, (effect,), 1.0) for effect in ("floor_viscosity", "floor_centring", "wind")),
)
# Run once, after the "heading" statistic was added (its bound from the calibration nulls): other seeds again.
HELD_OUT_2 = (
    *(("cube", seed, (), 1.0) for seed in (7, 8)),
    *((shape, 4, (), 1.0) for shape in ("dodecahedron", "octahedron", "tetrahedron", "icosahedron")),
    *(("cube", 2, ("anisotropic_friction",), strength) for strength in (1.0, 1.5, 2.0)),
    ("tetrahedron", 5, ("anisotropic_friction",), 2.0),
    ("dodecahedron", 5, ("anisotropic_friction",), 2.0),
    ("dodecahedron", 5, ("wind",), 1.0),
    ("octahedron", 5, ("coriolis",), 1.0),
    ("tetrahedron", 5, ("floor_viscosity",), 2.0),
    ("icosahedron", 5, ("floor_centring",), 1.0),
)
# Nulls of the independent generator: (shape, seed, recorded velocities). Seeds 901-910; the blind sets use 101-616.
INDEPENDENT_NULLS = (
    *(
        (shape, 901 + n, True)
        for n, shape in enumerate(
            ("cube", "plate", "brick", "tetrahedron", "octahedron", "dodecahedron", "icosahedron")
        )
    ),
    ("cube", 908, False),
    ("plate", 909, False),
    ("icosahedron", 910, False),
)
# The sets whose nulls set the bounds; the others are held out.
BOUND_SETS = ("calibration", "independent_nulls")
SETS = {
    "calibration": (*NULLS, *EFFECTS),
    "independent_nulls": INDEPENDENT_NULLS,
    "held_out": (*HELD_OUT_NULLS, *HELD_OUT_EFFECTS),
    "held_out_2": HELD_OUT_2,
}
REAL_CUBE = ROOT / "assets" / "contactnets_cube"


def case_name(shape: str, seed: int, effects: tuple[str, ...], strength: float) -> str:
    return f"{shape}_seed{seed}_{'+'.join(effects) or 'null'}_{strength:g}"


def cases(which: str) -> list[tuple[str, Path]]:
    """(name, recordings directory) of every case of a set, generating the synthetic ones that are missing."""
    found = []
    if which == "independent_nulls":
        for shape, seed, velocities in INDEPENDENT_NULLS:
            case = {"shape": shape, "seed": seed, "effect": None, "strength": 0.0, "velocities": velocities}
            path = independent_generator.generate_case(case, DATA / "independent")
            found.append((f"independent_{shape}_seed{seed}_null" + ("" if velocities else "_novel"), path))
        return found
    for shape, seed, effects, strength in SETS[which]:
        name = case_name(shape, seed, effects, strength)
        path = DATA / name
        if not (path / "meta.json").exists():
            generate_dataset(
                SHAPES[shape],
                path,
                variant=name,
                seed=seed,
                effects=effects,
                effect_strength=strength,
                workers=1,
                progress=False,
            )
        found.append((name, path))
    return [*found, ("real_cube", REAL_CUBE)] if which == "calibration" else found


def _cached(cache: Path, keys: list[str]) -> dict:
    """A base's cached fit (values, robust scale), if it was made for these parameters."""
    stored = json.loads(cache.read_text()) if cache.exists() else {}
    return stored if stored.get("keys") == keys else {}


def _store(cache: Path, keys: list[str], values: np.ndarray, scale: float, seconds: float) -> None:
    cache.parent.mkdir(parents=True, exist_ok=True)
    atomic.write_text(cache, json.dumps({"keys": keys, "values": values.tolist(), "scale": scale, "fit_s": seconds}))


def _slug(label: str) -> str:
    return label.replace(" (", "_").replace(" contact)", "").replace(" ", "_")


def _fit_once(steps: Diagnosis, hypothesis: Hypothesis, cache: Path, fit) -> tuple[Hypothesis, np.ndarray]:
    """A base's values from its cache, with the robust scale fit_base calibrated on train (both fits are scored with
    it), or `fit()` (hypothesis, values), cached."""
    stored = _cached(cache, hypothesis.keys())
    if stored:
        steps.train_fit.scale = steps.val_fit.scale = stored["scale"]
        return hypothesis, np.array(stored["values"])
    started = time.perf_counter()
    hypothesis, values = fit()
    _store(cache, hypothesis.keys(), values, steps.train_fit.scale, time.perf_counter() - started)
    return hypothesis, values


def fitted(name: str, path: Path) -> tuple[Diagnosis, Hypothesis, np.ndarray]:
    """The diagnosis steps with the diagnosis' own MuJoCo base fitted at the quick budget, from the cache when it has
    them."""
    steps = Diagnosis(read_recordings(path).for_models(["train", "val", "test"]), Budget())
    base, values = _fit_once(steps, Hypothesis(steps.dataset.n_bodies), DATA / "cache" / f"{name}.json", steps.fit_base)
    return steps, base, values


def fitted_bases(name: str, path: Path, engines: list[str]) -> list[tuple[str, Diagnosis, Hypothesis, np.ndarray]]:
    """(label, steps, base, values) of every base of `engines`: MuJoCo's as fitted(); every other engine's contact
    options searched as diagnosis.contact_law searches them (from the MuJoCo fit's robust scale), then each refitted on
    steps of its own as the pipeline refits the base it names on (Diagnosis.use_engine, fit_base from the law)."""
    steps, base, values = fitted(name, path)
    bases = [("mujoco", steps, base, values)] if "mujoco" in engines else []
    for engine_name in (e for e in engines if e != "mujoco"):
        options = engine_bases(engine_name, steps.dataset.n_bodies, len(steps.dataset.joints))
        caches = {option.label: DATA / "cache" / f"{name}_{_slug(option.label)}.json" for option in options}
        uncached = [
            o for o in options if not _cached(caches[o.label], Hypothesis(steps.dataset.n_bodies, base=o).keys())
        ]
        # every option's law is searched in one call (as contact_law does), only if one of them is not cached
        laws = (
            {c.label: c for c in contact_law.fit_engines(steps, base, values, ("mujoco", engine_name))[0]}
            if uncached
            else {}
        )
        for option in options:
            own = Diagnosis(steps.dataset, Budget())
            own.train_fit.scale = own.val_fit.scale = steps.train_fit.scale
            own.use_engine(engine_name, engine(engine_name).library_effects(steps.dataset))
            law = laws.get(option.label)
            hypothesis, law_values = _fit_once(
                own,
                Hypothesis(steps.dataset.n_bodies, base=option),
                caches[option.label],
                lambda own=own, law=law: own.fit_base(law.hypothesis, law.values),
            )
            bases.append((option.label, own, hypothesis, law_values))
    return bases


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="run the cases whose name contains this")
    parser.add_argument("--set", default="calibration", choices=sorted(SETS), help="which cases")
    parser.add_argument(
        "--engines", nargs="+", default=["mujoco"], choices=contact_law.ENGINES, help="the bases' engines"
    )
    parser.add_argument("--fit-only", action="store_true", help="generate and fit the base simulators, no check")
    args = parser.parse_args()
    torch.set_num_threads(1)
    out = DATA / f"results_{args.set}.json"
    results = json.loads(out.read_text()) if out.exists() else {}  # {base label: {case: record}}
    for name, path in cases(args.set):
        if args.only not in name:
            continue
        for label, steps, base, values in fitted_bases(name, path, args.engines):
            if args.fit_only:
                print(name, label, "fitted", flush=True)
                continue
            started = time.perf_counter()
            record = predictable.check(steps, base, values)
            record["check_s"] = time.perf_counter() - started
            world = open_world.explain(steps, base, values)
            record["open_world"] = {key: world.get(key) for key in ("passes", "val_improvement", "ci95")}
            steps.close()
            # read again before writing, under a lock: two runs of the same set on different cases (--only) keep
            # each other's records
            out.parent.mkdir(parents=True, exist_ok=True)
            with open(out.with_suffix(".lock"), "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                results = json.loads(out.read_text()) if out.exists() else {}
                results.setdefault(label, {})[name] = record
                atomic.write_text(out, json.dumps(results, indent=1))
            print(f"{name:42s} {label:28s} {record['check_s']:5.1f} s  {record['sentence']}", flush=True)
    for label, records in results.items():
        print(f"\n## base: {label}\n")
        print(predictable.calibration_table(records))
    print(null_bounds())


def null_bounds() -> str:
    """NULL_GAIN_BOUNDS as the null records of BOUND_SETS give them, per base: per statistic, the largest
    upper end of the val and test intervals over the nulls, plus the margin, rounded up to 0.001; with the null that
    set it. And how many of a base's nulls the open-world correction passed on (each a false alarm)."""
    by_base: dict[str, dict[str, dict]] = {}
    for which in BOUND_SETS:
        results = DATA / f"results_{which}.json"
        for label, records in (json.loads(results.read_text()) if results.exists() else {}).items():
            by_base.setdefault(label, {}).update({n: r for n, r in records.items() if "_null" in n})
    lines = ["NULL_GAIN_BOUNDS = {"]
    for label, nulls in by_base.items():
        world = sum(bool((record.get("open_world") or {}).get("passes")) for record in nulls.values())
        lines.append(f'    "{label}": {{  # {len(nulls)} nulls; the open-world correction passed on {world}')
        for statistic in predictable.STATISTICS:
            worst, name = max(
                (max(nulls[n][split]["statistics"][statistic]["ci95"][1] for split in ("val", "test")), n)
                for n in nulls
            )
            bound = math.ceil((worst + predictable.NULL_MARGIN) * 1000) / 1000
            lines.append(f'        "{statistic}": {bound:.3f},  # {name}: {worst:.3f}')
        lines.append("    },")
    return "\n".join([*lines, "}"])


if __name__ == "__main__":
    main()
