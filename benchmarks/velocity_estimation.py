"""How much the protocol's velocity estimate matters under tracking noise: backward difference vs least-squares fit.

For each noise level the dataset is observed as `observation.noise_mm` observes it (recorded velocities dropped),
the context velocities are estimated both ways, and MuJoCo with fixed parameters is rolled out from each; the rollout
is scored against the clean recording (synthetic data). Prints the velocity error at the last context frame and the
rollout position / rotation error. python benchmarks/velocity_estimation.py [--variant frictioncubes_0.5]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from contactbench.config import REPO_ROOT
from contactbench.evaluation.scoring import score_model
from contactbench.kinematics import estimate_velocities, fit_velocities
from contactbench.models.analytical import MujocoContactModel
from contactbench.observation import Observation
from contactbench.protocol import Context, make_context
from contactbench.recordings import read_recordings


class FromVelocities(MujocoContactModel):
    """MuJoCo with fixed parameters, started from context velocities estimated by `estimator`."""

    def __init__(self, estimator, **kwargs):
        super().__init__(**kwargs)
        self.estimator = estimator

    def rollout(self, scene, context: Context) -> np.ndarray:
        velocities = self.estimator(context.poses, scene.dt)
        return super().rollout(scene, replace(context, velocities=velocities))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default=str(REPO_ROOT / "data" / "frictioncubes" / "friction=0.5"))
    parser.add_argument("--preset", default="mujoco_default")
    parser.add_argument("--context", type=int, default=6)
    args = parser.parse_args()
    clean = read_recordings(args.dataset, ["test"])
    truth = clean.split("test")
    true_velocity = truth.velocities[:, args.context - 1]
    print(f"{clean.name}, test split ({truth.n_trajectories} tosses), {args.preset}, {args.context} context frames")
    print("noise mm | estimator | lin. velocity RMS error m/s | ang. velocity RMS error rad/s | pos_err | rot_err rad")
    for noise in (0.0, 0.5, 1.0, 2.0, 5.0):
        observed = Observation(noise_mm=noise, seed=0).observe(clean)
        for name, estimator in (("backward difference", estimate_velocities), ("least squares", fit_velocities)):
            context = make_context(observed.split("test"), observed.dt, args.context)
            error = estimator(context.poses, observed.dt)[:, -1] - true_velocity
            model = FromVelocities(estimator, name=args.preset, preset=args.preset)
            score = score_model(
                model, observed, "test", args.context, dataset_name=clean.name, variant="noise", truth=truth
            ).metrics.summary
            linear = np.sqrt((error[..., :3] ** 2).sum(-1).mean())
            angular = np.sqrt((error[..., 3:] ** 2).sum(-1).mean())
            print(
                f"{noise:8g} | {name:19} | {linear:8.3f} | {angular:8.3f} | "
                f"{score['pos_err']:.4f} | {score['rot_err_rad']:.4f}"
            )


if __name__ == "__main__":
    main()
