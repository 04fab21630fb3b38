"""Learning curves of the mesh GNNs on this machine: held-out (val) rollout error against training wall time.

Trains `gnn` (rigid, budget=quick) and `gnn_paper` (§4.3 as printed, budget=quick's network, given the same number
of steps) on frictioncubes μ = 0.5 and on the real cube through the real pipeline (runs.train), then writes
curves.csv and learning_curves.png beside the runs. Val only: the test split is the report's. A run folder that
already holds a finished run (fitted.json) is read, not trained again: link a matrix run there to reuse it.
    python benchmarks/gnn_learning_curve.py [--out outputs/benchmarks/gnn_learning_curve] [--budget quick]
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from contactbench import runs
from contactbench.config import CONFIG_DIR, REPO_ROOT
from contactbench.evaluation.figures import learning_curve_figure

VARIANTS = ("frictioncubes_0.5", "contactnets_cube")
MODELS = ("gnn", "gnn_paper")
SCHEDULE = ("max_steps", "val_check_interval", "val_rollouts")  # gnn_paper runs on gnn's


def composed(model: str, variant: str, budget: str) -> DictConfig:
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(
            config_name="train", overrides=[f"model={model}", f"variant={variant}", f"budget={budget}", "resume=false"]
        )


def curve(run_dir: Path) -> list[tuple[float, float, float]]:
    """(training seconds, val rollout position error, val rollout rotation error) at every validation of a run."""
    # a setting chosen on val logged its curves under its name (checkpoints/<setting>/best.ckpt)
    checkpoint = Path(json.loads((run_dir / "fitted.json").read_text())["checkpoint"])
    setting = f"{checkpoint.parent}/" if checkpoint.parent != Path() else ""
    with open(run_dir / "csv" / "metrics.csv", newline="") as handle:
        rows = [row for row in csv.DictReader(handle) if row.get(f"{setting}train/seconds")]  # the validations
    # runs logged before the one selection callback (ValRollouts) named the keys val/rollout_{pos,rot}_err
    prefix = setting + ("val/" if any(row.get(f"{setting}val/pos_err") for row in rows) else "val/rollout_")
    return [
        (float(row[f"{setting}train/seconds"]), float(row[f"{prefix}pos_err"]), float(row[f"{prefix}rot_err"]))
        for row in rows
        if row.get(f"{prefix}pos_err")
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "outputs" / "benchmarks" / "gnn_learning_curve")
    parser.add_argument("--budget", default="quick")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--models", nargs="+", default=list(MODELS))
    parser.add_argument("--draw-only", action="store_true", help="train nothing: draw the runs already in --out")
    args = parser.parse_args()
    curves, table = {}, []
    schedule = {key: composed("gnn", VARIANTS[0], args.budget).model.budgets[args.budget][key] for key in SCHEDULE}
    for variant in args.variants:
        for model in args.models:
            run_dir = args.out / f"{model}_{variant}"
            cfg = composed(model, variant, args.budget)
            if model == "gnn_paper":  # the same steps and validations as gnn: the curves then span similar times
                cfg.model.budgets[args.budget].update(schedule)
            started = time.perf_counter()
            if (run_dir / "fitted.json").is_file() or args.draw_only:
                val_pos_err = json.loads((run_dir / "val" / "metrics.json").read_text())["pos_err"]
            else:
                val_pos_err = runs.train(cfg, run_dir)
            points = curve(run_dir)
            curves[(model, cfg.dataset.name)] = points
            table.append(
                {
                    "model": model,
                    "variant": variant,
                    "wall_s": round(time.perf_counter() - started, 1),
                    "val_pos_err": round(val_pos_err, 4),
                }
            )
            print(
                f"{model:10s} {variant:18s} wall {table[-1]['wall_s']:7.1f} s  val pos_err {val_pos_err:.4f}  curve "
                f"{points}",
                flush=True,
            )
    with open(args.out / "curves.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["model", "dataset", "train_seconds", "val_pos_err", "val_rot_err"])
        for (model, dataset), points in curves.items():
            writer.writerows([model, dataset, *point] for point in points)
    print(f"wrote {learning_curve_figure(curves, args.out / 'learning_curves.png')} and {args.out / 'curves.csv'}")


if __name__ == "__main__":
    main()
