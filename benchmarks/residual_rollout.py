"""What the residual model's closed loop costs: its rollout against MuJoCo's own batched rollout, in the same run.

Both roll the real cube's val tosses out from the protocol's context with the same contact parameters; the residual
model steps MuJoCo one frame at a time (one native call for all tosses per frame) and runs its features, network and
projection in between. Prints seconds and the ratio. python benchmarks/residual_rollout.py [--repeats 3]
"""

from __future__ import annotations

import argparse

import torch
from metrics_speed import best_time  # a sibling script: python benchmarks/... puts benchmarks/ on the path

from contactbench.config import REPO_ROOT
from contactbench.models.analytical import preset_parameters
from contactbench.models.residual.contact_model import ResidualContactModel
from contactbench.models.residual.module import ResidualModule
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.sim.rollout import rollout_context


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    dataset = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["train", "val"])
    context = make_context(dataset.split("val"), dataset.dt, 6)
    parameters = preset_parameters("acosta2022", dataset.n_bodies)
    module = ResidualModule(dataset.for_models(["train", "val"]), 6, sysid={})
    module.feature_std.fill_(1.0)  # an untrained network costs what a trained one does
    scene = dataset.for_models()
    engine = best_time(lambda: rollout_context(scene, context, parameters), args.repeats)
    alone = ResidualContactModel(parameters, None, contact_margin=0.01)
    stepped = best_time(lambda: alone.rollout(scene, context), args.repeats)
    corrected = ResidualContactModel(parameters, module.predict, contact_margin=0.01)
    full = best_time(lambda: corrected.rollout(scene, context), args.repeats)
    frames = int((context.lengths - context.n_context).sum())
    print(f"real cube val: {len(context.lengths)} tosses, {frames} predicted frames; best of {args.repeats}")
    print(f"MuJoCo batched rollout (mujoco.rollout, whole horizon): {engine:.3f} s")
    print(f"residual loop, no correction (one native call per frame): {stepped:.3f} s  ratio {stepped / engine:.1f}x")
    print(f"residual loop with features, network, projection:        {full:.3f} s  ratio {full / engine:.1f}x")


if __name__ == "__main__":
    main()
