"""A learned impact map in place of MuJoCo's impact response: does it beat identified MuJoCo on val rollouts?

The residual model's closing alternative (docs/DIFFERENTIABLE.md): where training a correction through whole tosses
fails, learn the part MuJoCo gets most wrong, the impact. A body is *impacting* at a frame when one of its vertices
moves down faster than `--min-speed` and would pass below the floor within the frame in free flight. At those
frames only, an MLP maps the state before the step to the velocity after it (a body-frame velocity change on top
of MuJoCo's step, so MuJoCo's own impulse is replaced, not corrected: the network does not see it), projected like
the residual's correction (no vertex near the floor driven down, no kinetic energy gained); every other frame is
identified MuJoCo's. The map is regressed on the train split's impact frames (recorded state before, recorded pose
after), stopped on the val split's, and scored by rolling the whole val split out from the shared protocol's
context, beside MuJoCo alone. The `state+step` rows let the network see MuJoCo's step as well (a correction of it).

    python train.py model=sysid dataset=contactnets_cube budget=quick        # the identified MuJoCo it builds on
    python benchmarks/residual_impact_map.py --fitted outputs/train/sysid/contactnets_cube/real/budget=quick,seed=0
"""

from __future__ import annotations

import argparse
import json
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import nn

from contactbench.config import REPO_ROOT
from contactbench.kinematics import world_vertices
from contactbench.models.residual import correction
from contactbench.models.residual.contact_model import ResidualContactModel
from contactbench.models.residual.correction import Bodies
from contactbench.models.residual.windows import transitions
from contactbench.models.selection import rollout_errors
from contactbench.models.sysid.search_space import SearchSpace
from contactbench.recordings import read_recordings
from contactbench.sim.rollout import MujocoRollouts

CONTEXT_FRAMES = 6  # the shared protocol's


def impacting(bodies: Bodies, qpos: np.ndarray, qvel: np.ndarray, min_speed: float) -> np.ndarray:
    """[..., K] bodies with a vertex moving down faster than min_speed that free flight puts below the floor in a
    frame."""
    out = np.zeros(qpos.shape[:-1], dtype=bool)
    for k, vertices in enumerate(bodies.vertices):
        placed = world_vertices(qpos[..., k, :], vertices)
        speed = correction.vertical_velocities(qpos[..., k, :], qvel[..., k, None, :], placed - qpos[..., k, None, :3])
        height = placed[..., 2] - bodies.floor_z
        following = height + (speed[..., 0, :] + bodies.gravity[2] * bodies.dt) * bodies.dt
        out[..., k] = ((following < 0) & (speed[..., 0, :] < -min_speed)).any(axis=-1)
    return out


class ImpactMap(ResidualContactModel):
    """Identified MuJoCo whose step is overridden, body by body, at impact frames by the learned map."""

    def __init__(self, parameters, predict, min_speed: float, contact_margin: float = 0.01):
        super().__init__(parameters, predict, contact_margin)
        self.min_speed = min_speed

    def step(self, simulator, bodies, qpos, qvel):
        n, n_bodies = qpos.shape[:2]
        qpos1, qvel1, _ = simulator.step(self.parameters, qpos.reshape(n, -1), qvel.reshape(n, -1))
        qpos1, qvel1 = qpos1.reshape(n, n_bodies, 7), qvel1.reshape(n, n_bodies, 6)
        hit = impacting(bodies, qpos, qvel, self.min_speed)
        if not hit.any():
            return qpos1, qvel1
        inputs = correction.features(bodies, qpos, qvel, qpos1, qvel1).reshape(n * n_bodies, -1)
        change = np.nan_to_num(self.predict(inputs)).reshape(n, n_bodies, 6) * hit[..., None]
        return correction.corrected(bodies, qpos, qvel, qpos1, qvel1, change, self.contact_margin)


def fit_map(train, val, columns, angular_only: bool, seed: int, steps: int = 3000):
    """An MLP (2 x 128, SiLU) regressed on standardised train samples, the weights of its best val loss kept; the
    predictor, that loss and the val loss of predicting no change (MuJoCo's own step)."""
    (x_train, y_train), (x_val, y_val) = train, val
    mean, std = x_train[:, columns].mean(0), x_train[:, columns].std(0) + 1e-6
    target_std = y_train.std(0) + 1e-6
    kept_parts = np.r_[np.zeros(3) if angular_only else np.ones(3), np.ones(3)]  # angular only: linear left to MuJoCo

    def standardised(x):
        return torch.as_tensor((x[:, columns] - mean) / std, dtype=torch.float32)

    torch.manual_seed(seed)
    network = nn.Sequential(nn.Linear(len(mean), 128), nn.SiLU(), nn.Linear(128, 128), nn.SiLU(), nn.Linear(128, 6))
    optimiser = torch.optim.Adam(network.parameters(), lr=1e-3)
    inputs, targets = standardised(x_train), torch.as_tensor(y_train / target_std * kept_parts, dtype=torch.float32)
    val_inputs, val_targets = standardised(x_val), torch.as_tensor(y_val / target_std * kept_parts, dtype=torch.float32)
    generator = torch.Generator().manual_seed(seed)
    best, kept = np.inf, None
    unchanged = float((val_targets**2).mean())
    for step in range(steps):
        batch = torch.randint(0, len(inputs), (256,), generator=generator)
        loss = ((network(inputs[batch]) - targets[batch]) ** 2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step % 100 == 99:
            with torch.no_grad():
                val_loss = float(((network(val_inputs) - val_targets) ** 2).mean())
            if val_loss < best:
                best, kept = val_loss, {name: value.clone() for name, value in network.state_dict().items()}
    network.load_state_dict(kept)

    def predict(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return network(standardised(x)).numpy().astype(np.float64) * target_std * kept_parts

    return predict, best, unchanged


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recordings", type=Path, default=REPO_ROOT / "assets" / "contactnets_cube")
    parser.add_argument("--fitted", type=Path, required=True, help="a `model=sysid` run folder (its fitted.json)")
    parser.add_argument("--min-speed", type=float, nargs="+", default=[0.3, 1.0], help="m/s")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    dataset = read_recordings(args.recordings, ["train", "val"]).for_models(["train", "val"])
    bodies = Bodies.of(dataset)
    space = SearchSpace(dataset.n_bodies)
    fitted = json.loads((args.fitted / "fitted.json").read_text())["parameters"]
    parameters = space.from_vector([fitted[name] for name in space.names])
    simulator = MujocoRollouts(dataset)
    alone = rollout_errors(ResidualContactModel(parameters, None, 0.01), dataset, "val", CONTEXT_FRAMES)
    print(f"{args.recordings.name}, SysID {space.describe(parameters)}")
    print(f"val rollouts, MuJoCo alone: position {alone['pos_err']:.4f} widths, rotation {alone['rot_err']:.4f} rad")
    state_columns = np.setdiff1d(np.arange(bodies.n_features), np.arange(bodies.n_features)[correction.STEP_CHANGE])
    print("min speed | inputs | output | impacting (train) | one-step val loss (no change) | val pos | val rot | s")
    train_bodies = len(transitions(dataset.split("train"), bodies, simulator, parameters)[0])
    for min_speed in args.min_speed:
        started = time.perf_counter()
        impacts = partial(impacting, bodies, min_speed=min_speed)
        train, val = (
            transitions(dataset.split(name), bodies, simulator, parameters, impacts) for name in ("train", "val")
        )
        share = len(train[0]) / train_bodies
        for inputs, columns in (("state", state_columns), ("state+step", np.arange(bodies.n_features))):
            for output, angular_only in (("all", False), ("angular", True)):
                predict, one_step, unchanged = fit_map(train, val, columns, angular_only, args.seed)
                model = ImpactMap(parameters, predict, min_speed)
                errors = rollout_errors(model, dataset, "val", CONTEXT_FRAMES)
                print(
                    f"{min_speed} | {inputs} | {output} | {share:.3f} | {one_step:.3f} ({unchanged:.3f}) | "
                    f"{errors['pos_err']:.4f} | {errors['rot_err']:.4f} | {time.perf_counter() - started:.0f}"
                )


if __name__ == "__main__":
    main()
