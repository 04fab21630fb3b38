"""Does a fitted GNN's body come to rest, and does it stay out of the floor? Two failures its position error mixes.

For each GNN run folder given (a `train.py model=gnn` run: fitted.json and its checkpoint) on a single-body dataset,
rolled out over the val split from the benchmark's 6 context frames:

- creep: of the tosses whose recorded body is at rest at the end (under 1 cm/s over the last 5 frames), the share
  whose prediction still moves faster than that, and the predicted bodies' mean final speed;
- fall-through: the share of tosses whose prediction ends deeper in the floor than the deepest frame of the train
  split (PyBullet's sliding bodies sit up to 2 cm inside the floor, docs/RESULTS.md);
- stopping from a recorded slide: started from the first frames of each val toss where the body lies flat and slides
  at 0.1–0.3 m/s, its speed 60 frames later (the recorded bodies have all stopped by then).

    python benchmarks/gnn_coming_to_rest.py --data data/frictioncubes/friction=0.25 --runs outputs/train/gnn/...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from contactbench import metrics, restore, rotations
from contactbench.config import CONFIG_DIR
from contactbench.ground import Ground
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings

CONTEXT_FRAMES = 6
AT_REST = 0.01  # m/s
SLIDING = (0.1, 0.3)  # m/s
FLAT = np.cos(np.radians(2.0))
LATER = 60  # frames


def final_speed(poses: np.ndarray, dt: float) -> np.ndarray:
    """Mean speed [N] of the first body over the last 5 frames of poses [N, T, K, 7]."""
    return np.linalg.norm(np.diff(poses[:, -6:, 0, :3], axis=1), axis=-1).mean(axis=1) / dt


def sliding_starts(split) -> list[tuple[int, int]]:
    """(toss, frame) of each toss's first frame with a flat body sliding at SLIDING speeds and 5 flat frames before."""
    poses, velocities = split.poses[:, :, 0], split.velocities[:, :, 0]
    axis_heights = rotations.to_matrix(poses[..., 3:])[..., 2, :]  # one of the body's axes is vertical when flat
    flat = np.abs(axis_heights).max(axis=-1) > FLAT
    speed = np.linalg.norm(velocities[..., :2], axis=-1)
    starts = []
    for toss in range(split.n_trajectories):
        for frame in range(CONTEXT_FRAMES, split.lengths[toss] - LATER):
            if flat[toss, frame - 5 : frame + 1].all() and SLIDING[0] < speed[toss, frame] < SLIDING[1]:
                starts.append((toss, frame))
                break
    return starts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a single-body recordings folder")
    parser.add_argument("--runs", type=Path, nargs="+", required=True, help="GNN run folders fitted on --data")
    arguments = parser.parse_args()
    torch.set_num_threads(1)
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["model=gnn"])
    recordings = read_recordings(arguments.data, splits=["train", "val"])
    if recordings.n_bodies != 1:
        raise SystemExit(f"{arguments.data}: {recordings.n_bodies} bodies; this benchmark reads single-body data")
    train, val = recordings.split("train"), recordings.split("val")
    meshes, ground = [recordings.body_mesh(0)], Ground.of(recordings)
    starts = sliding_starts(val)
    frames = np.arange(train.n_frames)[None, :] < train.lengths[:, None]
    deepest = -metrics.ground_clearance(train.poses, meshes, ground)[frames].min()
    for run in arguments.runs:
        checkpoint = run / "checkpoints" / json.loads((run / "fitted.json").read_text())["checkpoint"]
        module = restore.load_module(cfg, recordings.for_models(), checkpoint)
        simulator, model = module.simulator, module.to_contact_model()

        predicted = model.rollout(recordings.scene, make_context(val, recordings.dt, CONTEXT_FRAMES))
        recorded = val.poses[:, : predicted.shape[1]]
        scores = metrics.compute_metrics(
            recorded, predicted, val.lengths, CONTEXT_FRAMES, meshes, recordings.floor_z, ground=ground
        )
        resting = final_speed(recorded, recordings.dt) < AT_REST
        speed = final_speed(predicted, recordings.dt)
        fell = -metrics.ground_clearance(predicted[:, -1], meshes, ground)[:, 0] > deepest

        history = simulator.velocity_history + 1
        context = np.stack([val.poses[toss, frame - history + 1 : frame + 1] for toss, frame in starts])
        later = simulator.rollout(torch.as_tensor(context), LATER).numpy()
        slide_speed = final_speed(later, recordings.dt)
        summary = {key: value * 1e3 if key.startswith("floor") else value for key, value in scores.summary.items()}
        moving_later = np.mean(slide_speed > AT_REST)
        print(
            f"{run}: val position {summary['pos_err']:.4f}, floor penetration "
            f"{summary['floor_penetration_m']:.2f} mm (recorded {summary['floor_penetration_true_m']:.2f})\n"
            f"  creep: {np.mean(speed[resting] > AT_REST):.2f} of the {resting.sum()} tosses at rest still move "
            f"(mean final speed {speed[resting].mean():.4f} m/s)\n"
            f"  fall-through: {fell.mean():.2f} end deeper than train's deepest frame ({deepest * 1e3:.1f} mm)\n"
            f"  from {len(starts)} recorded slides: {LATER} frames later {moving_later:.2f} still move "
            f"(mean {slide_speed.mean():.4f} m/s)"
        )


if __name__ == "__main__":
    main()
