"""Where sysid_mjx's gradient through contact is useful, and what randomized smoothing does for it.

At a few points of sysid's search space (box coordinates, models/sysid/gradient.py) — NGOpt's start, and the same
with the floor at the stiffest and the softest stiffness of Table 2c's range — compare MJX's forward-mode gradient
of the 16-frame window loss (the direction `model=sysid_mjx` steps along) with the slope of the objective that
selects, the C-MuJoCo val loss over whole val tosses (central differences, step 0.05 in each coordinate). Printed per
point and smoothing width sigma (the window gradient averaged over `--samples` coordinates drawn around the point with
that standard deviation; 0: the plain gradient): the cosine between the gradients of `--batches` disjoint window
batches (1: they agree, 0: noise), the cosine between their mean and the val slope (1: downhill on val), the change of
the val loss after a step of 0.1 along the mean gradient's direction, and seconds per gradient. `--at` adds the
points sysid runs found (their fitted.json), where the window and val objectives' optima part.

    python benchmarks/mjx_gradient_smoothing.py                                       # the real cube
    python benchmarks/mjx_gradient_smoothing.py --dataset data/frictioncubes/friction=0.5 \
        --at outputs/train/sysid/frictioncubes/friction=0.5/budget=quick,seed=0/fitted.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from contactbench.models.sysid.gradient import MjxWindows
from contactbench.models.sysid.objective import ConfigurationObjective
from contactbench.models.sysid.search_space import SearchSpace
from contactbench.recordings import read_recordings
from contactbench.sim.rollout import MujocoRollouts

CUBE_DATA = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, default=CUBE_DATA)
    parser.add_argument("--batches", type=int, default=8)
    parser.add_argument("--windows", type=int, default=64)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 0.1, 0.3])
    parser.add_argument("--samples", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--at", type=Path, nargs="*", default=[], help="sysid runs' fitted.json: their points too")
    args = parser.parse_args()

    dataset = read_recordings(args.dataset)
    space = SearchSpace(dataset.n_bodies)
    rollouts = MujocoRollouts(dataset)
    val = ConfigurationObjective(dataset, "val", 6, rollouts, position_exponent=2)
    windows = MjxWindows(dataset, space, 6, args.frames, position_exponent=2)
    box = windows.coordinates
    split = dataset.split("train")
    batches = [
        windows.windows(split, dataset.dt, args.windows, np.random.default_rng([args.seed, i]))
        for i in range(args.batches)
    ]

    def val_loss(coordinates: np.ndarray) -> float:
        return float(val([space.from_vector(box.to_vector(coordinates))]).losses[0])

    stiffness = space.n_bodies + 1  # the coordinate of log stiffness
    points = {"NGOpt's start": box.start.copy()}
    for name, edge in (("stiffest floor", 6.0), ("softest floor", -6.0)):
        points[name] = box.start.copy()
        points[name][stiffness] = edge
    for fitted in args.at:
        parameters = json.loads(fitted.read_text())["parameters"]
        points[f"fitted {len(points) - 2}"] = box.to_coordinates(np.array([parameters[n] for n in space.names]))
    windows.value_and_gradient(box.start, batches[0])  # compile
    print(f"dataset {args.dataset}: {args.batches} batches x {args.windows} windows of {args.frames} frames")
    print(
        "point           | k (N/m) | val loss | sigma | cos between batches | cos with val slope | val after | s/grad"
    )
    for name, point in points.items():
        here = val_loss(point)
        slope = np.array([(val_loss(point + 0.05 * e) - val_loss(point - 0.05 * e)) / 0.1 for e in np.eye(len(point))])
        rng = np.random.default_rng(args.seed)
        for sigma in args.sigmas:
            samples = 1 if sigma == 0 else args.samples
            gradients, seconds = [], []
            for batch in batches:
                started = time.perf_counter()
                drawn = [
                    windows.value_and_gradient(point + sigma * rng.standard_normal(len(point)), batch)[1]
                    for _ in range(samples)
                ]
                seconds.append((time.perf_counter() - started) / samples)
                gradients.append(np.mean(drawn, axis=0))
            agreement = np.mean([cosine(a, b) for i, a in enumerate(gradients) for b in gradients[i + 1 :]])
            mean = np.mean(gradients, axis=0)
            after = val_loss(point - 0.1 * mean / max(np.linalg.norm(mean), 1e-300))
            k = space.from_vector(box.to_vector(point)).floor_stiffness
            print(
                f"{name:15s} | {k:7.0f} | {here:8.4f} | {sigma:5.2f} | {agreement:19.3f} | "
                f"{cosine(mean, slope):18.3f} | {after:9.4f} | {np.median(seconds):.2f}"
            )
    rollouts.close()


if __name__ == "__main__":
    main()
