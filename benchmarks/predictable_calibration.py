"""Calibrate diagnosis.predictable on null datasets and show that it detects concealed effects.

Generates (once) null datasets (nothing concealed: cubes of several seeds and other solids) and datasets with one
concealed effect, fits the base simulator of each at the quick budget (once: the fitted values and robust scale are
cached as JSON under data/predictable/cache/, refitted when the base hypothesis' parameters change), runs
predictable.check on it and prints one line and one table row per dataset: each statistic's val and test gain with
the lower ends of their 95% intervals, which pass their null bounds, where and on what. On the calibration set it
also prints the bounds its nulls give (largest upper interval end + predictable.NULL_MARGIN), the values of
predictable.NULL_GAIN_BOUNDS. The held-out sets were run once each, after the bounds were set. Records are kept in
data/predictable/results_<set>.json (git-ignored, as everything under data/).

    python benchmarks/predictable_calibration.py                    # the calibration set (~20 s a case the first time)
    python benchmarks/predictable_calibration.py --set held_out     # other seeds, shapes and strengths
    python benchmarks/predictable_calibration.py --only cube_seed0  # the cases whose name contains it
    python benchmarks/predictable_calibration.py --fit-only         # generate and fit, no check
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from diagnosis_proof import SHAPES  # beside this script: the proof's shapes, at the same nominal contact

from contactbench.diagnosis import predictable
from contactbench.diagnosis.library import Hypothesis
from contactbench.diagnosis.state import Budget, Diagnosis
from contactbench.generation.generator import generate_dataset
from contactbench.recordings import read_recordings

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
SETS = {
    "calibration": (*NULLS, *EFFECTS),
    "held_out": (*HELD_OUT_NULLS, *HELD_OUT_EFFECTS),
    "held_out_2": HELD_OUT_2,
}
REAL_CUBE = ROOT / "assets" / "contactnets_cube"


def case_name(shape: str, seed: int, effects: tuple[str, ...], strength: float) -> str:
    return f"{shape}_seed{seed}_{'+'.join(effects) or 'null'}_{strength:g}"


def cases(which: str) -> list[tuple[str, Path]]:
    """(name, recordings directory) of every case of a set, generating the synthetic ones that are missing."""
    found = []
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


def fitted(name: str, path: Path) -> tuple[Diagnosis, Hypothesis, np.ndarray]:
    """The diagnosis steps with the base simulator fitted at the quick budget, from the cache when it has them."""
    steps = Diagnosis(read_recordings(path).for_models(["train", "val", "test"]), Budget())
    base = Hypothesis(steps.dataset.n_bodies)
    cache = DATA / "cache" / f"{name}.json"
    stored = json.loads(cache.read_text()) if cache.exists() else {}
    if stored.get("keys") == base.keys():  # a cache of another base hypothesis (its parameters changed) is refitted
        values = np.array(stored["values"])
        # fit_base leaves both fits scored with the robust scale calibrated on train
        steps.train_fit.scale = steps.val_fit.scale = stored["scale"]
    else:
        started = time.perf_counter()
        base, values = steps.fit_base()
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_text(
            json.dumps(
                {
                    "keys": base.keys(),
                    "values": values.tolist(),
                    "scale": steps.train_fit.scale,
                    "fit_s": time.perf_counter() - started,
                }
            )
        )
    return steps, base, values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="run the cases whose name contains this")
    parser.add_argument("--set", default="calibration", choices=sorted(SETS), help="which cases")
    parser.add_argument("--fit-only", action="store_true", help="generate and fit the base simulators, no check")
    args = parser.parse_args()
    torch.set_num_threads(1)
    results = {}
    out = DATA / f"results_{args.set}.json"
    if out.exists():
        results = json.loads(out.read_text())
    for name, path in cases(args.set):
        if args.only not in name:
            continue
        steps, base, values = fitted(name, path)
        if args.fit_only:
            print(name, "fitted", flush=True)
            continue
        started = time.perf_counter()
        record = predictable.check(steps, base, values)
        record["check_s"] = time.perf_counter() - started
        results[name] = record
        out.write_text(json.dumps(results, indent=1))
        print(f"{name:42s} {record['check_s']:5.1f} s  {record['sentence']}", flush=True)
    print(predictable.calibration_table(results))
    if args.set == "calibration":
        print(null_bounds(results))


def null_bounds(results: dict[str, dict]) -> str:
    """NULL_GAIN_BOUNDS as the null records give them: per statistic, the largest upper end of the val and test
    intervals over the nulls, plus the margin, rounded up to 0.001; with the null that set it."""
    nulls = [name for name in results if "_null_" in name]
    lines = [f"NULL_GAIN_BOUNDS from {len(nulls)} nulls = {{"]
    for statistic in predictable.STATISTICS:
        worst, name = max(
            (max(results[n][split]["statistics"][statistic]["ci95"][1] for split in ("val", "test")), n) for n in nulls
        )
        bound = math.ceil((worst + predictable.NULL_MARGIN) * 1000) / 1000
        lines.append(f'    "{statistic}": {bound:.3f},  # {name}: {worst:.3f}')
    return "\n".join([*lines, "}"])


if __name__ == "__main__":
    main()
