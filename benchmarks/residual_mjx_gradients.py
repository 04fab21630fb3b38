"""What reverse mode through MJX tells the residual correction, by window length: signal against noise, and cost.

On the real cube's train tosses, with the residual model's network as stage two starts it (statistics from the train
transitions, last layer zero: the identified MuJoCo itself), draw `--batches` disjoint batches of `--windows`
windows from recorded states for each window length and take the gradient of eq. (1) with respect to the weights
through the corrected MJX rollout (model.module.gradient=mjx). Printed per length: the mean window loss, the
gradient's size, the cosine between batches' gradients (1: every batch points the same way; 0: noise), the
fraction of the mean gradient left after averaging (its norm over the mean of the norms), jit compile seconds and
seconds per gradient; last, the same numbers for MuJoCo's finite-difference adjoint (`gradient: linearised`) at
its default 16 frames, with its seconds per gradient as the ratio's reference.

    python benchmarks/residual_mjx_gradients.py                 # lengths 4 16 64 134
    python benchmarks/residual_mjx_gradients.py --lengths 16 --batches 4
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from contactbench.models.residual.module import ResidualModule
from contactbench.models.residual.through_mjx import MjxResidualWindows
from contactbench.models.residual.windows import recorded_windows, segment_starts
from contactbench.recordings import read_recordings

CUBE_DATA = Path(__file__).resolve().parents[1] / "assets" / "contactnets_cube"


def flat(gradient) -> np.ndarray:
    return np.concatenate([part.ravel() for layer in gradient for part in layer])


def agreement(gradients: list[np.ndarray]) -> tuple[float, float, float]:
    """Mean norm, mean pairwise cosine, and |mean| / mean |g| of a list of gradients."""
    norms = np.array([np.linalg.norm(g) for g in gradients])
    unit = [g / max(n, 1e-300) for g, n in zip(gradients, norms)]
    cosines = [unit[i] @ unit[j] for i in range(len(unit)) for j in range(i + 1, len(unit))]
    return (
        float(norms.mean()),
        float(np.mean(cosines)),
        float(np.linalg.norm(np.mean(gradients, axis=0)) / norms.mean()),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--lengths", type=int, nargs="+", default=[4, 16, 64, 134])
    parser.add_argument("--batches", type=int, default=8)
    parser.add_argument("--windows", type=int, default=64)
    parser.add_argument("--fitted", type=Path, help="a sysid run's fitted.json (default: the parameters below)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    dataset = read_recordings(CUBE_DATA, ["train"])
    module = ResidualModule(dataset, 6, sysid={})
    # model=sysid's parameters at budget=quick, seed 0 (docs/RESULTS.md); --fitted reads another run's
    parameters = {
        "object_friction_0": 0.18756,
        "floor_friction": 0.21339,
        "floor_stiffness": 7471.8,
        "floor_damping": 143.94,
    }
    if args.fitted:
        parameters = json.loads(args.fitted.read_text())["parameters"]
    vector = [parameters[name] for name in module.space.names]
    module.parameters_vector.copy_(torch.as_tensor(vector, dtype=torch.float64))
    inputs, wanted = module.transitions("train")
    module.feature_mean.copy_(torch.as_tensor(inputs.mean(axis=0)))
    module.feature_std.copy_(torch.as_tensor(inputs.std(axis=0)).clamp_min(1e-6))
    module.target_std.copy_(torch.as_tensor(wanted.std(axis=0)).clamp_min(1e-6))

    split = dataset.split("train")
    starts = segment_starts(split)
    rng = np.random.default_rng(args.seed)
    drawn = starts[rng.permutation(len(starts))[: args.batches * args.windows]].reshape(args.batches, args.windows, 2)
    weights = MjxResidualWindows.weights(module)
    windows = MjxResidualWindows(dataset, module.identified, 0.01, module.hparams.max_correction, solver_iterations=10)
    print(
        f"real cube, {args.batches} batches x {args.windows} windows from recorded train states, network at its start"
    )
    print("frames | loss   | |grad|   | cosine between batches | |mean| / mean | compile s | s per gradient")
    for length in args.lengths:
        gradients, losses, seconds = [], [], []
        for segments in drawn:
            batch = recorded_windows(split, segments, length, dataset.dt)
            started = time.perf_counter()
            loss, gradient = windows.value_and_gradient(weights, *batch)
            seconds.append(time.perf_counter() - started)
            gradients.append(flat(gradient))
            losses.append(loss)
        norm, cosine, kept = agreement(gradients)
        print(
            f"{length:6d} | {np.mean(losses):.4f} | {norm:.2e} | {cosine:22.3f} | {kept:13.3f} | {seconds[0]:9.1f} | "
            f"{np.median(seconds[1:]):.2f}"
        )
    gradients, seconds = [], []
    for segments in drawn:
        module.zero_grad()
        started = time.perf_counter()
        module.rollout_loss("train", torch.as_tensor(segments)).backward()
        seconds.append(time.perf_counter() - started)
        layers = [layer for layer in module.network if hasattr(layer, "weight")]
        gradients.append(
            np.concatenate([p.grad.numpy().ravel() for layer in layers for p in (layer.weight, layer.bias)])
        )
    norm, cosine, kept = agreement(gradients)
    print(
        f"linearised MuJoCo (16 frames): |grad| {norm:.2e}, cosine {cosine:.3f}, |mean| / mean {kept:.3f}, "
        f"{np.median(seconds):.2f} s per gradient"
    )


if __name__ == "__main__":
    main()
