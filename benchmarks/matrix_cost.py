"""What one `make matrix` job of each model costs, against that model's floor, measured in the same run.

Each model is fitted and scored as one job of the matrix (`train.py model=<m> variant=<v> budget=quick test=true`,
a fresh process, one at a time, in a throw-away run tree), and its floor is timed right after it in this process:

- an engine-based model (MuJoCo, PyBullet, Drake; untuned, identified, the residual's MuJoCo): the bare engine rolling
  the same val and test tosses out once from the protocol's context, at the engine's default parameters (MuJoCo:
  one `mujoco.rollout` call; PyBullet and Drake: their bare stepping loops of bullet_rollout.py and
  drake_rollout.py); for a search (sysid, sysid_bullet, sysid_drake) its simulated train tosses are added, the bare
  val+test time per predicted frame times the frames the search asks for (evaluations x restarts x tosses per
  evaluation), an estimate marked "~";
- the GNN: the bare network's training step (forward + backward + Adam on the same graphs, gnn_speed.py) times its
  steps and its settings chosen on val;
- the hybrid model: its bare MLP's training step on a batch times the batches of the epochs the job trained (early
  stopping ends it before max_epochs).

Prints, per model: the job's wall seconds, the seconds inside the run (its signature.json to its test metrics: no
imports, no Hydra), the floor and the ratios. Floors cover a single free body (the default variant); the job's own
seconds hold for any variant.
    python benchmarks/matrix_cost.py                                   # the three untuned engines, sysid, hybrid
    python benchmarks/matrix_cost.py --models all                      # every model of experiment=matrix
    python benchmarks/matrix_cost.py --models gnn --variant contactnets_cube
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from metrics_speed import best_time  # a sibling script: python benchmarks/... puts benchmarks/ on the path

from contactbench.config import CONFIG_DIR, REPO_ROOT
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.sim.engines import engine

DEFAULT_MODELS = ["mujoco_default", "bullet_default", "drake_default", "sysid", "hybrid"]
ENGINE_OF = {  # the engine an engine-based model simulates with
    "mujoco_default": "mujoco",
    "sysid": "mujoco",
    "sysid_mjx": "mujoco",
    "residual": "mujoco",
    "bullet_default": "bullet",
    "sysid_bullet": "bullet",
    "drake_default": "drake",
    "sysid_drake": "drake",
}


def composed(overrides: list[str], hydra: bool = False):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("train", overrides=overrides, return_hydra_config=hydra)


def matrix_models() -> list[str]:
    return str(composed(["experiment=matrix"], hydra=True).hydra.sweeper.params.model).split(",")


def run_job(model: str, variant: str, budget: str, log_dir: Path) -> tuple[float, float | None, Path]:
    """Wall seconds of one train.py job, the seconds inside its run folder, and that folder."""
    run_dir = log_dir / "runs" / model
    command = [
        sys.executable,
        str(REPO_ROOT / "train.py"),
        f"model={model}",
        f"variant={variant}",
        f"budget={budget}",
        "test=true",
        f"paths.log_dir={log_dir}",
        f"hydra.run.dir={run_dir}",
    ]
    started = time.perf_counter()
    result = subprocess.run(command, cwd=REPO_ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - started
    metrics = run_dir / "test" / "metrics.json"
    if result.returncode != 0 or not metrics.is_file():
        sys.exit(f"{model}: the job failed (exit {result.returncode})\n{result.stderr[-3000:]}")
    inside = metrics.stat().st_mtime - (run_dir / "signature.json").stat().st_mtime
    return wall, inside, run_dir


def engine_floor(name: str, dataset, context_frames: int) -> tuple[float, int]:
    """Seconds of the bare engine rolling val and test out once from the protocol's context; predicted frames."""
    scene = dataset.for_models()
    contexts = [make_context(dataset.split(split), dataset.dt, context_frames) for split in ("val", "test")]
    poses0 = np.concatenate([context.poses[:, -1] for context in contexts])
    velocities0 = np.concatenate([context.velocities[:, -1] for context in contexts])
    lengths = np.concatenate([context.lengths for context in contexts])
    frames = int((lengths - context_frames).sum())
    steps = int(lengths.max()) - context_frames
    parameters = engine(name).default_parameters(scene.n_bodies)
    if name == "mujoco":
        import mujoco
        import mujoco.rollout

        from contactbench.sim.rollout import MujocoRollouts

        simulator = MujocoRollouts(scene)
        model = simulator.model(parameters)
        initial = simulator.initial_states(poses0, velocities0)
        data = [mujoco.MjData(model) for _ in range(simulator.nthread)]
        seconds = best_time(
            lambda: mujoco.rollout.rollout([model] * len(initial), data, initial, nstep=steps, persistent_pool=True),
            3,
        )
        return seconds, len(initial) * steps
    if scene.n_bodies != 1:
        sys.exit(f"the bare {name} loop here takes one free body; {dataset.name} has {scene.n_bodies}")
    if name == "bullet":
        from bullet_rollout import bare_loop

        seconds = sum(best_time(lambda context=context: bare_loop(scene, context), 1) for context in contexts)
        return seconds, frames
    from drake_rollout import bare_loop

    loop = bare_loop(scene, parameters, poses0, velocities0, steps)
    return best_time(loop, 1), len(poses0) * steps


def search_frames(cfg, dataset, context_frames: int) -> int:
    """Frames a SysID search simulates: evaluations x restarts x tosses per evaluation x their predicted frames."""
    module = cfg.model.module
    train = dataset.split("train")
    tosses = int(module.batch_trajectories or train.n_trajectories)
    per_toss = float(np.mean(train.lengths)) - context_frames
    return int(int(module.evaluations) * int(module.restarts) * tosses * per_toss)


def gnn_floor(cfg, dataset) -> tuple[float, str]:
    """The bare network's training steps: seconds per step x max_steps x settings chosen on val."""
    import torch
    from gnn_speed import training_samples_per_second

    from contactbench.models.gnn import cpu_kernels
    from contactbench.models.gnn.module import GNNModule

    cpu_kernels.pin()
    torch.set_num_threads(int(cfg.torch_threads or 1))
    torch.manual_seed(0)
    budget = cfg.model.budgets[cfg.budget.name]
    module = GNNModule(
        dataset,
        latent_size=int(budget.latent_size),
        message_passing_steps=int(budget.message_passing_steps),
        rigid=bool(cfg.model.module.rigid),
        velocity_history=int(cfg.model.module.velocity_history),
    )
    module.setup("fit")
    graphs = max(1, int(budget.batch_vertices) // module.simulator.scene.n_nodes)
    _, bare = training_samples_per_second(module, dataset, graphs, 50)
    settings = math.prod(len(values) for values in _leaves(cfg.model.get("choose_on_val"))) or 1
    steps = int(budget.max_steps)
    return graphs / bare * steps * settings, f"bare network step x {steps} steps x {settings} settings"


def _leaves(tree) -> list:
    if tree is None:
        return []
    if hasattr(tree, "items"):
        return [leaf for _, value in tree.items() for leaf in _leaves(value)]
    return [list(tree)]


def epochs_run(run_dir: Path) -> int | None:
    """Epochs the job trained (early stopping may end it before max_epochs), from its csv/metrics.csv."""
    path = run_dir / "csv" / "metrics.csv"
    if not path.is_file():
        return None
    with open(path, newline="") as file:
        epochs = [int(float(row["epoch"])) for row in csv.DictReader(file) if row.get("epoch")]
    return max(epochs) + 1 if epochs else None


def hybrid_floor(cfg, dataset, run_dir: Path) -> tuple[float, str]:
    """The bare MLP's training step on a batch x the batches of the epochs the job trained."""
    import torch

    from contactbench.models.hybrid import HybridDataModule, HybridModule

    torch.set_num_threads(int(cfg.torch_threads or 1))
    torch.manual_seed(0)
    batch_size = int(cfg.model.datamodule.batch_size)
    datamodule = HybridDataModule(dataset, context_frames=int(cfg.context_frames), batch_size=batch_size)
    datamodule.setup("fit")
    n_train = len(datamodule.arrays["train"][0])
    module = HybridModule(dataset, context_frames=int(cfg.context_frames))
    network = module.network
    inputs = torch.randn(batch_size, network[0].in_features)
    optimizer = torch.optim.Adam(network.parameters(), lr=float(cfg.model.module.lr))

    def step() -> None:
        optimizer.zero_grad()
        network(inputs).square().mean().backward()
        optimizer.step()

    step()
    started = time.perf_counter()
    for _ in range(50):
        step()
    per_step = (time.perf_counter() - started) / 50
    epochs = epochs_run(run_dir) or int(cfg.model.trainer.max_epochs)
    batches = math.ceil(n_train / batch_size)
    return per_step * batches * epochs, f"bare MLP step x {batches} batches x {epochs} epochs"


def floor(model: str, cfg, context_frames: int, run_dir: Path) -> tuple[float, str]:
    path = Path(cfg.dataset.path)
    if model == "gnn":
        return gnn_floor(cfg, read_recordings(path, ["train", "val"]).for_models(["train", "val"]))
    if model == "hybrid":
        return hybrid_floor(cfg, read_recordings(path, ["train", "val"]).for_models(["train", "val"]), run_dir)
    name = ENGINE_OF.get(model)
    if name is None:
        sys.exit(f"{model}: no floor is defined here (models: {', '.join([*ENGINE_OF, 'gnn', 'hybrid'])})")
    dataset = read_recordings(path, ["train", "val", "test"])
    seconds, frames = engine_floor(name, dataset, context_frames)
    what = f"bare {name}, val+test once"
    if model in ("sysid", "sysid_bullet", "sysid_drake"):
        searched = search_frames(cfg, dataset, context_frames)
        seconds += seconds / frames * searched
        what = f"~ bare {name}, val+test + the search's {searched:,} frames"
    return seconds, what


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=DEFAULT_MODELS, help="'all': every model of experiment=matrix")
    parser.add_argument("--variant", default="frictioncubes_0.5")
    parser.add_argument("--budget", default="quick")
    parser.add_argument("--keep", type=Path, default=None, help="run the jobs under this folder and keep it")
    args = parser.parse_args()
    models = matrix_models() if args.models == ["all"] else args.models
    if "residual" in models and "sysid" in models:  # the residual takes SysID's run of the same tree, as in the matrix
        models = sorted(models, key=lambda name: name == "residual")
    load = os.getloadavg()
    print(f"variant {args.variant}, budget {args.budget}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="matrix_cost_") as scratch:
        log_dir = args.keep or Path(scratch)
        for model in models:
            cfg = composed([f"model={model}", f"variant={args.variant}", f"budget={args.budget}"])
            wall, inside, run_dir = run_job(model, args.variant, args.budget, log_dir)
            seconds, what = floor(model, cfg, int(cfg.context_frames), run_dir)
            rows.append((model, wall, inside, seconds, what))
            print(f"  {model}: job {wall:.1f} s (inside the run {inside:.1f} s), floor {seconds:.2f} s", flush=True)
    print()
    print("| model | job wall s | inside the run s | floor s | job / floor | inside / floor | the floor |")
    print("|---|---|---|---|---|---|---|")
    for model, wall, inside, seconds, what in rows:
        print(
            f"| {model} | {wall:.1f} | {inside:.1f} | {seconds:.2f} | {wall / seconds:.1f} | {inside / seconds:.1f} "
            f"| {what} |"
        )
    load = os.getloadavg()
    print(f"load average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    main()
