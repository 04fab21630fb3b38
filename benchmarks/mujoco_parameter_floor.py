"""How close any one set of MuJoCo contact parameters gets to the real cube: a random search on the val split.

The residual model (issue 14) must reach position <= 0.20 widths and rotation <= 0.31 rad on the real cube's test
tosses. Its first stage is MuJoCo with one set of contact parameters. This script draws `--draws` sets from a box
wider than SysID's (sliding friction, floor stiffness and damping, plus torsional and rolling friction, which SysID
leaves at 0), rolls the whole val split out with each (the shared protocol: 6 context frames), and prints the best
sets by position and by rotation, with the Acosta et al. 2022 preset alongside. What it prints is the floor under
any correction that keeps MuJoCo's contact as it is.

    python benchmarks/mujoco_parameter_floor.py [--draws 300] [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from contactbench.config import REPO_ROOT
from contactbench.models.analytical import MujocoContactModel, preset_parameters
from contactbench.models.selection import rollout_errors
from contactbench.recordings import read_recordings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    dataset = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["train", "val"]).for_models(["train", "val"])
    acosta = preset_parameters("acosta2022", dataset.n_bodies)
    rng = np.random.default_rng(args.seed)
    rows = []
    for _ in range(args.draws):
        friction = rng.uniform(0.05, 0.6)
        parameters = dataclasses.replace(
            acosta,
            object_friction=(friction,),
            floor_friction=friction,
            floor_stiffness=float(np.exp(rng.uniform(np.log(200), np.log(5000)))),
            floor_damping=rng.uniform(10, 150),
            torsional_friction=float(rng.choice([0.0, 0.01, 0.03])),
            rolling_friction=float(rng.choice([0.0, 0.002, 0.005])),
        )
        errors = rollout_errors(MujocoContactModel("draw", parameters=parameters), dataset, "val", 6)
        rows.append((errors["pos_err"], errors["rot_err"], parameters))
    preset = rollout_errors(MujocoContactModel("acosta2022", parameters=acosta), dataset, "val", 6)
    print(f"real cube val, {args.draws} random parameter sets (seed {args.seed}); position in widths, rotation in rad")
    print(f"acosta2022 preset: {preset['pos_err']:.4f} / {preset['rot_err']:.3f}")
    for label, key in (("position", 0), ("rotation", 1)):
        print(f"best five by {label}:")
        for pos_err, rot_err, p in sorted(rows, key=lambda row: row[key])[:5]:
            print(
                f"  {pos_err:.4f} / {rot_err:.3f}  friction {p.floor_friction:.3f} stiffness {p.floor_stiffness:.0f} "
                f"damping {p.floor_damping:.1f} torsional {p.torsional_friction} rolling {p.rolling_friction}"
            )


if __name__ == "__main__":
    main()
