"""MuJoCo's own system-identification toolbox (model=mujoco_sysid) against the paper's NGOpt search (model=sysid), in
one run: the same Table 2c parameters, train tosses, eq. (1) and selection on val, on the real cube and on
frictioncubes μ = 0.5 (generated first if missing), through the real pipeline (runs.train with test=true). Prints
each fit's val loss (eq. 1), val and test errors and wall time (fit and scoring of val and test), the ratio of the
two models' wall times, and the toolbox's parameters with their intervals.
    python benchmarks/sysid_toolbox_vs_ngopt.py [--budget quick] [--out outputs/benchmarks/sysid_toolbox_vs_ngopt]

With --diff-steps it fits the toolbox once instead, at budget=quick's iterations on every train toss of the real cube,
for each finite-difference step given, from NGOpt's start with the floor friction low (as mujoco_sysid starts) and,
at the first step given, from NGOpt's start itself (both frictions 0.5): why the model's step and start are what they
are.
    python benchmarks/sysid_toolbox_vs_ngopt.py --diff-steps 0.03 1.5e-8 1e-3 0.1
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from contactbench import runs
from contactbench.config import CONFIG_DIR, REPO_ROOT
from contactbench.models.sysid.mujoco_toolbox import ToolboxSysIDModule, fit, start_vector
from contactbench.models.sysid.uncertainty import EquationOneResiduals
from contactbench.recordings import read_recordings

VARIANTS = ("contactnets_cube", "frictioncubes_0.5")
MODELS = ("sysid", "mujoco_sysid")
CUBE = REPO_ROOT / "assets" / "contactnets_cube"


def composed(model: str, variant: str, budget: str) -> DictConfig:
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(
            config_name="train",
            overrides=[f"model={model}", f"variant={variant}", f"budget={budget}", "test=true", "resume=false"],
        )


def fitted(model: str, variant: str, budget: str, run_dir: Path) -> dict:
    """One fit from scratch, scored on val and test; its numbers and wall time."""
    shutil.rmtree(run_dir, ignore_errors=True)
    cfg = composed(model, variant, budget)
    started = time.perf_counter()
    val_pos_err = runs.train(cfg, run_dir)
    wall = time.perf_counter() - started
    test = json.loads((run_dir / "test" / "metrics.json").read_text())
    record = json.loads((run_dir / "fitted.json").read_text())
    return {
        "variant": variant,
        "model": model,
        "val_loss": record["val_loss"],
        "val_pos_err": val_pos_err,
        "test_pos_err": test["pos_err"],
        "test_rot_err_rad": test["rot_err_rad"],
        "wall_s": wall,
        "fitted": record,
    }


def step_scan(steps: list[float], budget: str) -> None:
    """One least-squares fit per finite-difference step (and one from both frictions at 0.5), scored on val."""
    dataset = read_recordings(CUBE, ["train", "val"])
    max_iters = composed("mujoco_sysid", "contactnets_cube", budget).model.module.max_iters
    cases = [(step, True) for step in steps] + [(steps[0], False)]
    print(f"real cube, every train toss, {max_iters} iterations, one start; val loss is eq. (1) on every val toss")
    print("| start | diff_step | iterations | evaluations | val loss | seconds | parameters |")
    print("|---|---|---|---|---|---|---|")
    for step, floor_low in cases:
        module = ToolboxSysIDModule(
            dataset, 6, restarts=1, max_iters=max_iters, train_trajectories=None, val_trajectories=None, diff_step=step
        )
        rollouts = module.rollouts()
        train = EquationOneResiduals(dataset, "train", 6, rollouts, position_exponent=2)
        start = start_vector(module, 0)
        if not floor_low:  # NGOpt's own start: the floor's friction at the centre, as the object's
            start[module.space.names.index("floor_friction")] = start[0]
        result = fit(module, train, start)
        found = module.space.from_vector(result["vector"])
        val_loss = float(module.objective("val", rollouts)([found]).losses[0])
        rollouts.close()
        label = "floor friction low" if floor_low else "both frictions 0.5"
        print(
            f"| {label} | {step:g} | {result['iterations']} | {result['evaluations']} | {val_loss:.4f} | "
            f"{result['seconds']:.1f} | {', '.join(f'{v:.4g}' for v in result['vector'])} |",
            flush=True,
        )


def intervals(record: dict) -> str:
    """The toolbox's parameters with their intervals, as one line."""
    entries = record["uncertainty"]["parameters"]
    shown = []
    for name, entry in entries.items():
        span = "not identifiable" if entry["interval"] is None else "[{:.4g}, {:.4g}]".format(*entry["interval"])
        shown.append(f"{name} {entry['value']:.4g} {span} ({entry['unit']})")
    return f"{record['uncertainty']['confidence']:.0%} intervals: " + "; ".join(shown)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "outputs" / "benchmarks" / "sysid_toolbox_vs_ngopt")
    parser.add_argument("--budget", default="quick")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--diff-steps", nargs="+", type=float, help="fit the toolbox once per step instead")
    args = parser.parse_args()
    if args.diff_steps:
        step_scan(args.diff_steps, args.budget)
        return
    rows = []
    for variant in args.variants:
        for model in MODELS:
            rows.append(fitted(model, variant, args.budget, args.out / f"{model}_{variant}"))
            row = rows[-1]
            print(f"done: {model} on {variant} in {row['wall_s']:.1f} s", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(f"\nbudget={args.budget}, seed 0; wall time: fit, then val and test scored (runs.train with test=true)\n")
    print("| variant | model | val loss (eq. 1) | val pos_err | test pos_err / rot_err_rad | wall s |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['variant']} | `{row['model']}` | {row['val_loss']:.4f} | {row['val_pos_err']:.4f} | "
            f"{row['test_pos_err']:.4f} / {row['test_rot_err_rad']:.3f} | {row['wall_s']:.1f} |"
        )
    print()
    for variant in args.variants:
        by_model = {row["model"]: row for row in rows if row["variant"] == variant}
        ratio = by_model["mujoco_sysid"]["wall_s"] / by_model["sysid"]["wall_s"]
        chosen = ", ".join(by_model["sysid"]["fitted"]["optimizer"]["chosen"])
        print(f"{variant}: wall time mujoco_sysid / sysid = {ratio:.2f} (NGOpt ran {chosen})")
        print(f"  mujoco_sysid {intervals(by_model['mujoco_sysid']['fitted'])}")
        print(f"  sysid {by_model['sysid']['fitted']['parameters']}")


if __name__ == "__main__":
    main()
