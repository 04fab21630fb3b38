"""What bounds the real elbow: an oracle first impact, an oracle at every impact, and the chaos floor (issue 45).

The identified engine of a train run (default: `sysid_bullet` on `contactnets_elbow`) rolls a split out from the
shared protocol's context, scored with the project's own metric (`metrics.compute_metrics`, as `evaluate.py` does):

- *baseline*: the run's own rollouts (its val score).
- *oracle first impact, k*: at the first floor impact after the context the simulated state is replaced by the
  recorded state (pose and the recording's velocities) k frames later, and the engine goes on from there: what a
  perfect first-impact map would reach. The impact is the first frame at or after the context at which the lowest
  vertex of either link is within `--margin` of the floor (lowest-vertex height, `metrics.lowest_vertex_height`),
  the frame before it being above the margin.
- *oracle every impact*: the same reset k frames after every recorded contact onset: a vertex of either link coming
  within `--margin` of the floor after it was above `--arm` since its last touch (a bounce, a bar slapping down).
- *chaos floor*: the context's last velocity perturbed by Gaussian noise of the size measured in the recordings (per
  link and component, the median over the train tosses of the residual standard deviation of a line fitted in time to
  the six context frames' recorded velocities), `--draws` draws; the project's metric between each perturbed rollout
  and the unperturbed one, averaged over draws: error any deterministic model keeps from the tracker's noise alone.
- *learned map* (`--learned`): a ridge regression fitted on the train tosses' first impacts, from the recorded state
  the frame before the impact (heights, orientations and velocities in the base link's heading frame) to the
  recorded state k frames after it minus the engine's continuation of that pre-impact state (positions, rotation
  vectors, velocities); plugged in at the engine's own first impact (the same rule on the simulated frames), chosen
  on val over k and the penalty; with the control "engine reset, no map" (the engine's own state put back) and the
  map's R2 on the split's recorded impacts per link and part. `--split test` scores one chosen (k, alpha) once.

Prints every figure and writes nothing. Deterministic given `--seed`.

    python train.py model=sysid_bullet dataset=contactnets_elbow budget=quick     # the run it reads
    python benchmarks/elbow_impact_ceiling.py                                      # val, ~1 min on 2 cores
    python benchmarks/elbow_impact_ceiling.py --limit 40 --draws 2                 # a quick look
    python benchmarks/elbow_impact_ceiling.py --learned --ks 1 2 3 4 --alphas 10 100 1000 1e4 1e5 1e7  # part 3
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from contactbench import rotations
from contactbench.config import REPO_ROOT
from contactbench.kinematics import world_vertices
from contactbench.metrics import compute_metrics, lowest_vertex_height
from contactbench.models.sysid.search_space import search_space
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.scene import Split
from contactbench.sim.engines import engine

RUN = "outputs/train/sysid_bullet/contactnets_elbow/real/budget=quick,seed=0"


def identified(run: Path, n_bodies: int, n_joints: int):
    """(engine name, substeps, parameters) of a SysID run folder, from its config and fitted.json."""
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    name = str(cfg.model.module.engine)
    fitted = json.loads((run / "fitted.json").read_text())["parameters"]
    space = search_space(name, n_bodies, n_joints)
    return name, int(cfg.observation.frame_stride), space.from_vector([fitted[n] for n in space.names])


def subset(split: Split, count: int | None) -> Split:
    """The first `count` tosses (all without a count)."""
    take = slice(0, count)
    return Split(poses=split.poses[take], lengths=split.lengths[take], velocities=split.velocities[take])


def first_impacts(split: Split, meshes, floor_z: float, margin: float, context: int) -> np.ndarray:
    """[N] the first frame >= context whose lowest vertex (either link) is within margin of the floor, the frame
    before it above; -1 where there is none."""
    low = lowest_vertex_height(split.poses, meshes, floor_z).min(axis=-1)  # [N, T]
    onset = (low <= margin) & (np.roll(low, 1, axis=1) > margin) & split.valid_mask()
    onset[:, :context] = False
    return np.where(onset.any(axis=1), onset.argmax(axis=1), -1)


def every_onset(split: Split, meshes, floor_z: float, margin: float, arm: float, context: int) -> list[list[int]]:
    """Per toss, the frames >= context at which some vertex comes within margin of the floor, having been above arm
    since its last touch (each vertex is armed at the start)."""
    heights = [world_vertices(split.poses[..., k, :], mesh.vertices)[..., 2] - floor_z for k, mesh in enumerate(meshes)]
    heights = np.concatenate(heights, axis=-1)  # [N, T, K*V] every vertex's height above the floor
    onsets = []
    for n, length in enumerate(split.lengths):
        armed = np.ones(heights.shape[-1], dtype=bool)
        frames = []
        for t in range(int(length)):
            touch = heights[n, t] <= margin
            if (touch & armed).any() and t >= context:
                frames.append(t)
            armed = (armed & ~touch) | (heights[n, t] > arm)
        onsets.append(frames)
    return onsets


def roll_with_resets(rollouts, params, split: Split, base: np.ndarray, resets: list[list[int]]) -> np.ndarray:
    """Predicted poses [N, horizon, K, 7]: the protocol's rollout `base`, the state replaced by the recorded one at
    each toss's reset frames (sorted, inside the toss, after the context) and simulated on from there."""
    predicted = base.copy()
    horizon = base.shape[1]
    pass_index = 0
    while True:
        active = [n for n, frames in enumerate(resets) if len(frames) > pass_index]
        if not active:
            return predicted
        starts = np.array([resets[n][pass_index] for n in active])
        ends = np.array(
            [resets[n][pass_index + 1] if len(resets[n]) > pass_index + 1 else horizon for n in active]
        )  # each segment is simulated up to (not including) the next reset
        steps = int((ends - starts - 1).max())
        poses0, velocities0 = split.poses[active, starts], split.velocities[active, starts]
        if steps > 0:
            simulated = rollouts.simulate(params, poses0, velocities0, steps).poses[0]
        for i, n in enumerate(active):
            predicted[n, starts[i]] = poses0[i]
            span = ends[i] - starts[i] - 1
            if span > 0:
                predicted[n, starts[i] + 1 : ends[i]] = simulated[i, :span]
        pass_index += 1


def heading(poses: np.ndarray) -> np.ndarray:
    """[M, K, 4] the rotation about world z that takes away the base link's yaw (the floor's symmetry), per link."""
    frame = rotations.to_matrix(poses[:, 0, 3:])
    yaw = np.arctan2(frame[:, 1, 0], frame[:, 0, 0])
    return np.repeat(rotations.from_axis_angle(np.array([0.0, 0.0, 1.0]), -yaw)[:, None], poses.shape[1], axis=1)


def features(poses: np.ndarray, velocities: np.ndarray, floor_z: float) -> np.ndarray:
    """[M, F] a pre-impact state [M, K, 7] / [M, K, 6] in the heading frame: heights, orientations, velocities."""
    h = heading(poses)
    parts = [poses[..., 2] - floor_z, rotations.to_matrix(rotations.multiply(h, poses[..., 3:])).reshape(len(h), -1)]
    parts += [rotations.rotate(h, velocities[..., :3]).reshape(len(h), -1)]
    return np.concatenate(parts + [rotations.rotate(h, velocities[..., 3:]).reshape(len(h), -1)], axis=1)


def state_residual(h, poses, velocities, engine_poses, engine_velocities) -> np.ndarray:
    """[M, K*12] recorded minus engine state in the heading frames h [M, K, 4]: position, rotation vector, [v, w]."""
    turn = rotations.to_rotation_vector(rotations.multiply(poses[..., 3:], rotations.conjugate(engine_poses[..., 3:])))
    parts = [poses[..., :3] - engine_poses[..., :3], turn, velocities[..., :3] - engine_velocities[..., :3]]
    parts.append(velocities[..., 3:] - engine_velocities[..., 3:])
    return np.concatenate([rotations.rotate(h, part) for part in parts], axis=-1).reshape(len(h), -1)


def apply_residual(h, engine_poses, engine_velocities, residual) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of state_residual: the engine's state corrected by a residual [M, K*12]."""
    back = rotations.conjugate(h)
    r = [rotations.rotate(back, part) for part in np.split(residual.reshape(h.shape[:2] + (12,)), 4, axis=-1)]
    turned = rotations.multiply(rotations.from_rotation_vector(r[1]), engine_poses[..., 3:])
    poses = np.concatenate([engine_poses[..., :3] + r[0], turned], axis=-1)
    return poses, engine_velocities + np.concatenate([r[2], r[3]], axis=-1)


def ridge(x: np.ndarray, y: np.ndarray, alpha: float):
    """A ridge regression on standardised features (intercept not penalised): the predictor."""
    mean, std, y_mean = x.mean(0), x.std(0) + 1e-9, y.mean(0)
    z = (x - mean) / std
    weights = np.linalg.solve(z.T @ z + alpha * np.eye(z.shape[1]), z.T @ (y - y_mean))
    return lambda q: ((q - mean) / std) @ weights + y_mean


def impact_samples(rollouts, params, split: Split, impacts: np.ndarray, k: int, floor_z: float):
    """Train samples: features of the recorded state the frame before the first impact, and the residual of the
    recorded state k frames after the impact against the engine's continuation of that pre-impact state."""
    use = np.flatnonzero((impacts >= 1) & (impacts + k < split.lengths))
    pre, post = impacts[use] - 1, impacts[use] + k
    result = rollouts.simulate(params, split.poses[use, pre], split.velocities[use, pre], k + 1)
    h = heading(split.poses[use, pre])
    x = features(split.poses[use, pre], split.velocities[use, pre], floor_z)
    y = state_residual(
        h, split.poses[use, post], split.velocities[use, post], result.poses[0][:, k], result.velocities[0][:, k]
    )
    return x, y


def learned_rollout(rollouts, params, base, split: Split, meshes, floor_z, args, k, predict) -> np.ndarray:
    """The engine's rollout `base` (SimulationResult) with its state k frames after its own first impact corrected by
    the learned map of its state the frame before, and simulated on from there."""
    poses, velocities = base.poses[0].copy(), base.velocities[0].copy()
    simulated = Split(poses=poses, lengths=split.lengths)
    impacts = first_impacts(simulated, meshes, floor_z, args.margin, args.context_frames)
    use = np.flatnonzero((impacts >= 1) & (impacts + k < split.lengths))
    pre, post = impacts[use] - 1, impacts[use] + k
    h = heading(poses[use, pre])
    residual = predict(features(poses[use, pre], velocities[use, pre], floor_z))
    poses[use, post], velocities[use, post] = apply_residual(h, poses[use, post], velocities[use, post], residual)
    resets = [[] for _ in split.lengths]
    for n, frame in zip(use, post):
        resets[n] = [int(frame)]
    source = Split(poses=poses, lengths=split.lengths, velocities=velocities)
    return roll_with_resets(rollouts, params, source, base.poses[0], resets)


def velocity_noise(split: Split, context_frames: int) -> np.ndarray:
    """[K, 6] per link and component, the median over tosses of the residual std (dof-corrected) of a line fitted in
    time to the context frames' recorded velocities."""
    velocities = split.velocities[:, :context_frames]
    design = np.stack([np.ones(context_frames), np.arange(context_frames)], axis=1)
    hat = design @ np.linalg.pinv(design)
    residual = velocities - np.einsum("ij,njkc->nikc", hat, velocities)
    return np.median(np.sqrt((residual**2).sum(axis=1) / (context_frames - 2)), axis=0)


def score(recorded: Split, predicted: np.ndarray, dataset, context_frames: int) -> tuple[float, float]:
    """(position error in widths, rotation error in rad): the project's metric, as evaluate.py scores a split."""
    meshes = [dataset.body_mesh(k) for k in range(dataset.n_bodies)]
    truth = recorded.poses[:, : predicted.shape[1]]
    metrics = compute_metrics(
        truth, predicted, recorded.lengths, context_frames, meshes, dataset.floor_z, joints=dataset.joints
    )
    return metrics.summary["pos_err"], metrics.summary["rot_err_rad"]


def ceilings(args, dataset, meshes, split, context, rollouts, params, result, report) -> None:
    """Part 1 and 2: the oracle first impact for each k (also pose or velocities alone), the oracle every impact,
    the chaos floor."""
    c, floor_z, base = args.context_frames, dataset.floor_z, result.poses[0]
    impacts = first_impacts(split, meshes, floor_z, args.margin, c)
    found = impacts >= 0
    print(f"first impact found in {found.sum()} of {len(impacts)} tosses; frame median {np.median(impacts[found])}")
    low = lowest_vertex_height(split.poses, meshes, floor_z).min(axis=-1)
    jump = np.diff(split.velocities[..., 2], axis=1).max(axis=-1)  # [N, T-1] the links' largest rise in v_z
    near = [int(np.argmax(jump[n, i - 4 : i + 5])) - 3 for n, i in enumerate(impacts) if i >= 4]
    print(
        f"largest v_z jump relative to the impact frame: median {np.median(near):+.0f} frames, within 0..1 in "
        f"{np.mean([0 <= d <= 1 for d in near]):.0%}; lowest vertex there median "
        f"{1e3 * np.median(low[found, impacts[found]]):.1f} mm"
    )
    for k in args.ks:
        resets = [[i + k] if 0 <= i and i + k < length else [] for i, length in zip(impacts, split.lengths)]
        report(f"oracle first impact k={k}", roll_with_resets(rollouts, params, split, base, resets))
        for part, poses, velocities in (
            ("pose", split.poses, result.velocities[0]),
            ("velocity", base, split.velocities),
        ):
            t = base.shape[1]
            source = Split(poses=poses[:, :t], lengths=split.lengths, velocities=velocities[:, :t])
            report(f"  recorded {part} only k={k}", roll_with_resets(rollouts, params, source, base, resets))
    onsets = every_onset(split, meshes, floor_z, args.margin, args.arm, c)
    k = args.every_k
    resets = [sorted({t + k for t in frames if t + k < length}) for frames, length in zip(onsets, split.lengths)]
    counts = [len(r) for r in resets]
    report(
        f"oracle every impact k={k}",
        roll_with_resets(rollouts, params, split, base, resets),
        f"({np.mean(counts):.1f} resets a toss, median {np.median(counts):.0f})",
    )
    sigma = velocity_noise(dataset.split("train"), c) * args.noise_scale
    print("velocity noise per link [vx vy vz (m/s) wx wy wz (rad/s)]:", np.round(sigma, 3).tolist())
    rng = np.random.default_rng(args.seed)
    unperturbed = Split(poses=base, lengths=split.lengths)
    spread = []
    for _ in range(args.draws):
        velocities = context.velocities.copy()
        velocities[:, -1] += rng.normal(size=velocities[:, -1].shape) * sigma
        perturbed = rollouts.rollout_context(replace(context, velocities=velocities), params).poses[0]
        spread.append(score(unperturbed, perturbed, dataset, c))
    mean, std = np.mean(spread, axis=0), np.std(spread, axis=0)
    label = f"chaos floor ({args.draws} draws)"
    print(f"{label:<32} {mean[0]:.4f} widths / {mean[1]:.3f} rad (draws' std {std[0]:.3f} / {std[1]:.3f})")


def learned(args, dataset, meshes, split, base, rollouts, params, report) -> None:
    """Part 3: a ridge first-impact map fitted on train, for each k and alpha, plugged into the engine."""
    train = dataset.split("train")
    impacts = first_impacts(train, meshes, dataset.floor_z, args.margin, args.context_frames)
    held_out = first_impacts(split, meshes, dataset.floor_z, args.margin, args.context_frames)
    for k in args.ks:
        x, y = impact_samples(rollouts, params, train, impacts, k, dataset.floor_z)
        if len(args.alphas) > 1:  # the control: the reset alone, the engine's own state put back (no map)
            zero = lambda q, width=y.shape[1]: np.zeros((len(q), width))  # noqa: E731
            kept = learned_rollout(rollouts, params, base, split, meshes, dataset.floor_z, args, k, zero)
            report(f"engine reset k={k} (no map)", kept)
            x_held, y_held = impact_samples(rollouts, params, split, held_out, k, dataset.floor_z)
            parts = y_held.reshape(len(y_held), -1, 4, 3)
        for alpha in args.alphas:
            predict = ridge(x, y, alpha)
            predicted = learned_rollout(rollouts, params, base, split, meshes, dataset.floor_z, args, k, predict)
            r2 = ""
            if len(args.alphas) > 1:  # the map on the split's recorded impacts: R2 per link x [pos, rot, v, w]
                miss = ((parts - predict(x_held).reshape(parts.shape)) ** 2).sum(-1).mean(0)
                r2 = f"R2 {np.round(1 - miss / (parts**2).sum(-1).mean(0), 2).tolist()}"
            report(f"learned map k={k} alpha={alpha:g}", predicted, r2)


def prepare(args, split_name: str):
    """The dataset (train and `split_name`), its meshes, the scored tosses and their context, the identified engine's
    rollouts and parameters, and a `report(label, predicted)` that prints the project's score of a prediction."""
    dataset = read_recordings(REPO_ROOT / args.dataset, ["train", split_name])
    meshes = [dataset.body_mesh(k) for k in range(dataset.n_bodies)]
    split = subset(dataset.split(split_name), args.limit)
    context = make_context(split, dataset.dt, args.context_frames)
    name, substeps, params = identified(REPO_ROOT / args.run, dataset.n_bodies, len(dataset.joints))
    rollouts = engine(name).rollouts(dataset.scene, substeps=substeps)
    print(f"{name}, {args.run}, {split_name}: {len(split.lengths)} tosses")

    def report(label: str, predicted: np.ndarray, extra: str = "") -> None:
        value = score(split, predicted, dataset, args.context_frames)
        print(f"{label:<32} {value[0]:.4f} widths / {value[1]:.3f} rad {extra}", flush=True)

    return dataset, meshes, split, context, rollouts, params, report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", default=RUN, help="a SysID train run folder (fitted.json, .hydra/config.yaml)")
    parser.add_argument("--dataset", default="assets/contactnets_elbow")
    parser.add_argument("--split", default="val", choices=["val", "test"], help="test: only with --learned, once")
    parser.add_argument("--limit", type=int, default=None, help="score only the split's first LIMIT tosses")
    parser.add_argument("--ks", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="frames after the impact")
    parser.add_argument("--every-k", type=int, default=1, help="frames after every onset for the every-impact oracle")
    parser.add_argument("--margin", type=float, default=0.005, help="m: a vertex this near the floor touches it")
    parser.add_argument("--arm", type=float, default=0.01, help="m: a vertex above this may touch again")
    parser.add_argument("--draws", type=int, default=8, help="perturbed rollouts for the chaos floor")
    parser.add_argument("--noise-scale", type=float, default=1.0, help="the measured velocity noise times this")
    parser.add_argument("--learned", action="store_true", help="part 3 (the learned map) instead of parts 1-2")
    parser.add_argument("--alphas", type=float, nargs="+", default=[1, 10, 100, 1000, 1e5], help="ridge penalties")
    parser.add_argument("--context-frames", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.split == "test" and not (args.learned and len(args.ks) == 1 and len(args.alphas) == 1):
        parser.error("test is scored once, for the learned map chosen on val: --learned with one --ks and one --alphas")
    dataset, meshes, split, context, rollouts, params, report = prepare(args, args.split)
    started = time.perf_counter()

    try:
        result = rollouts.rollout_context(context, params)
        report("baseline", result.poses[0])
        if args.learned:
            learned(args, dataset, meshes, split, result, rollouts, params, report)
        else:
            ceilings(args, dataset, meshes, split, context, rollouts, params, result, report)
    finally:
        rollouts.close()
    print(f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
