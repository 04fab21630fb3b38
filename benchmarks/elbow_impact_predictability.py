"""Is the real elbow's first impact predictable from the state before it? Three measurements on val (issue 45).

The sequel to `elbow_impact_ceiling.py` (whose pieces it imports): the same identified engine (default `sysid_bullet`
on `contactnets_elbow`, seed 0), the same first-impact rule (the first frame after the context whose lowest vertex is
within `--margin` of the floor), the same heading frame (the base link's yaw taken away) and the same state parts as
the learned map's targets: per link position (m), rotation (rad), linear (m/s) and angular velocity (rad/s).

- *Analogues* (`--analogues`): the pre-impact state (the recorded frame before the first impact: heights,
  orientations relative to gravity, the hinge's angle and rate, velocities, all in the heading frame, each component
  standardised by its train spread) of every val toss against every train toss (and train against train), and the
  distance between the same pairs' recorded outcomes k frames after the impact (displacement from the pre-impact
  position, orientation relative to gravity, velocities, in each toss's own heading frame). Half the mean squared
  outcome distance (a variogram) is fitted, linear in the pre-impact distance, over the nearest pairs and extrapolated
  to distance zero: the nugget is the variance of the outcome no function of the pre-impact state can predict; beside
  it the engine's own error from the same recorded pre-impact state. `--oracle-noise` then scores the oracle first
  impact with the recorded state k frames after the impact perturbed by that unpredictable part (Gaussian, each part's
  nugget), to put it in the project's metric.
- *Sensitivity* (`--sensitivity`): the state the frame before the first impact (the engine's own rollout's, and the
  recorded one) perturbed by the tracker's noise: pose noise measured as the residual of a quadratic fitted in time to
  the context poses (per link: position, rotation vector about the middle frame; median over train tosses), velocity
  noise as `elbow_impact_ceiling.velocity_noise`; `--draws` draws; the spread of the engine's state k frames after the
  impact beside the engine's error there, and each perturbed rollout scored against the unperturbed one.
- *Ensemble mean* (`--ensemble N`): the chaos floor's N perturbed-context rollouts (the context's last velocity
  perturbed by the measured velocity noise, drawn exactly as `elbow_impact_ceiling.py` draws them for the same seed),
  averaged per frame: positions by their mean, each link's orientation by the normalised sign-aligned quaternion mean;
  scored with the project's metric. The mean is an average of trajectories, not one physical trajectory: its two
  links need not meet at the hinge, and the gap between their hinge anchors is measured.

Prints every figure and writes nothing. Deterministic given `--seed`. Val only: test is never scored.

    python benchmarks/elbow_impact_predictability.py --analogues --oracle-noise     # ~2 min on 2 cores
    python benchmarks/elbow_impact_predictability.py --sensitivity
    python benchmarks/elbow_impact_predictability.py --ensemble 8
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from elbow_impact_ceiling import (  # a sibling script: python benchmarks/... puts benchmarks/ on the path
    RUN,
    apply_residual,
    features,
    first_impacts,
    heading,
    impact_samples,
    prepare,
    roll_with_resets,
    score,
    state_residual,
    velocity_noise,
)

from contactbench import rotations
from contactbench.kinematics import hinge_coordinates
from contactbench.metrics import compute_metrics, joint_errors
from contactbench.protocol import make_context
from contactbench.scene import Split

PARTS = ("pos m", "rot rad", "v m/s", "w rad/s")


def pre_state(poses, velocities, floor_z, joints) -> np.ndarray:
    """[M, F] the learned map's features of a state [M, K, 7] / [M, K, 6], and each hinge's cos, sin and rate."""
    extra = []
    for joint in joints:
        angle, rate = hinge_coordinates(
            poses[:, joint.parent],
            velocities[:, joint.parent],
            poses[:, joint.child],
            velocities[:, joint.child],
            joint,
        )
        extra += [np.cos(angle), np.sin(angle), rate]
    return np.concatenate([features(poses, velocities, floor_z), np.stack(extra, axis=1)], axis=1)


def outcome(split: Split, use, pre, post):
    """The recorded outcome at frames post of tosses use, in the heading frame of frames pre: displacement from the
    pre-impact position [M, K, 3], orientation [M, K, 4], linear and angular velocity [M, K, 3] each."""
    h = heading(split.poses[use, pre])
    poses, velocities = split.poses[use, post], split.velocities[use, post]
    shift = rotations.rotate(h, poses[..., :3] - split.poses[use, pre, :, :3])
    return (
        shift,
        rotations.multiply(h, poses[..., 3:]),
        rotations.rotate(h, velocities[..., :3]),
        rotations.rotate(h, velocities[..., 3:]),
    )


def outcome_distance(a, b, i, j) -> np.ndarray:
    """[P, K, 4] squared distance per link and part between outcomes a[i] and b[j] (rotation: the angle squared)."""
    shift = ((a[0][i] - b[0][j]) ** 2).sum(-1)
    turn = rotations.to_rotation_vector(rotations.multiply(a[1][i], rotations.conjugate(b[1][j])))
    return np.stack(
        [shift, (turn**2).sum(-1), ((a[2][i] - b[2][j]) ** 2).sum(-1), ((a[3][i] - b[3][j]) ** 2).sum(-1)], -1
    )


def impact_frames(split: Split, meshes, floor_z, args, k):
    """Tosses with a first impact and k frames after it inside the toss: (indices, pre-impact frames, post frames)."""
    impacts = first_impacts(split, meshes, floor_z, args.margin, args.context_frames)
    use = np.flatnonzero((impacts >= 1) & (impacts + k < split.lengths))
    return use, impacts[use] - 1, impacts[use] + k


def engine_error(rollouts, params, split, meshes, floor_z, args, k) -> np.ndarray:
    """[M, K, 4] squared error per link and part of the engine's continuation of the recorded pre-impact state, k
    frames after the impact (the learned map's target)."""
    impacts = first_impacts(split, meshes, floor_z, args.margin, args.context_frames)
    _, y = impact_samples(rollouts, params, split, impacts, k, floor_z)
    return (y.reshape(len(y), -1, 4, 3) ** 2).sum(-1)


def binned(d, gamma, cluster, edges, fit_bins: int, rng, boots: int):
    """Per bin of pre-impact distance: mean distance, pairs, RMS outcome distance / sqrt 2 [K, 4] (sqrt of the mean
    semivariance); and the line through the nearest fit_bins bins' (distance, RMS) extrapolated to distance 0 [K, 4],
    with a 90% interval from resampling the pairs' first tosses (`cluster`)."""
    index = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, len(edges) - 2)

    def table(weights):
        count = np.bincount(index, weights, minlength=len(edges) - 1)
        mean_d = np.bincount(index, weights * d, minlength=len(edges) - 1) / np.maximum(count, 1e-12)
        flat = gamma.reshape(len(d), -1)
        g = np.stack([np.bincount(index, weights * flat[:, c], len(edges) - 1) for c in range(flat.shape[1])], -1)
        rms = np.sqrt(g / np.maximum(count, 1e-12)[:, None]).reshape((-1,) + gamma.shape[1:])
        slope_design = np.stack([np.ones(fit_bins), mean_d[:fit_bins]], axis=1)
        coef = np.linalg.lstsq(slope_design, rms[:fit_bins].reshape(fit_bins, -1), rcond=None)[0]
        return mean_d, count, rms, coef[0].reshape(gamma.shape[1:])

    mean_d, count, rms, intercept = table(np.ones(len(d)))
    tosses = np.unique(cluster)
    draws = []
    for _ in range(boots):
        weights = np.bincount(rng.choice(tosses, len(tosses)), minlength=cluster.max() + 1)[cluster].astype(float)
        draws.append(table(weights)[3])
    low, high = np.quantile(np.stack(draws), [0.05, 0.95], axis=0) if boots else (intercept, intercept)
    return mean_d, count, rms, intercept, low, high


def analogues(args, dataset, meshes, train, split, rollouts, params, report) -> None:
    """Measurement 1: outcome distance against pre-impact distance, extrapolated to 0, the engine beside it."""
    floor_z, joints = dataset.floor_z, dataset.joints
    pose_sigma = pose_noise(train, args.context_frames)
    velocity_sigma = velocity_noise(train, args.context_frames)
    for k in args.ks:
        (tu, tpre, tpost), (vu, vpre, vpost) = (impact_frames(s, meshes, floor_z, args, k) for s in (train, split))
        xt = pre_state(train.poses[tu, tpre], train.velocities[tu, tpre], floor_z, joints)
        xv = pre_state(split.poses[vu, vpre], split.velocities[vu, vpre], floor_z, joints)
        mean, std = xt.mean(0), xt.std(0) + 1e-12
        zt, zv = (xt - mean) / std, (xv - mean) / std
        noisy = perturbed_states(
            np.random.default_rng(args.seed),
            split.poses[vu, vpre],
            split.velocities[vu, vpre],
            pose_sigma,
            velocity_sigma,
        )
        noise_d = np.linalg.norm((pre_state(*noisy, floor_z, joints) - mean) / std - zv, axis=1)
        ot, ov = outcome(train, tu, tpre, tpost), outcome(split, vu, vpre, vpost)
        i, j = np.meshgrid(np.arange(len(zv)), np.arange(len(zt)), indexing="ij")
        pairs = {"val-train": (zv, zt, ov, ot, i.ravel(), j.ravel())}
        i, j = np.triu_indices(len(zt), 1)
        pairs["train-train"] = (zt, zt, ot, ot, i, j)
        engine_sq = engine_error(rollouts, params, split, meshes, floor_z, args, k).mean(0)  # [K, 4]
        print(
            f"\nk={k}: {len(vu)} val / {len(tu)} train impacts, {zt.shape[1]} standardised pre-impact features; "
            f"the tracker's noise moves a val pre-impact state by {np.median(noise_d):.2f} (median); engine RMS error "
            "from the recorded pre-impact state, per link:"
        )
        for link in range(engine_sq.shape[0]):
            print(f"  link {link}  " + "  ".join(f"{p} {v:.3g}" for p, v in zip(PARTS, np.sqrt(engine_sq[link]))))
        found = {}
        for name, (za, zb, oa, ob, i, j) in pairs.items():
            d = np.linalg.norm(za[i] - zb[j], axis=1)
            gamma = 0.5 * outcome_distance(oa, ob, i, j)  # [P, K, 4] semivariance per pair
            edges = np.unique(np.quantile(d, [0, *args.quantiles]))
            rng = np.random.default_rng(args.seed)
            mean_d, count, rms, intercept, low, high = binned(d, gamma, i, edges, args.fit_bins, rng, args.boots)
            print(f"  {name} pairs ({len(d)}), nearest pre-impact distance {d.min():.2f} (median {np.median(d):.2f})")
            print("    pre-dist  pairs   " + "  ".join(f"{p:>17}" for p in PARTS) + "   RMS outcome distance / sqrt 2")
            for b in range(len(count)):
                cells = "  ".join(f"{rms[b, 0, c]:8.3g} {rms[b, 1, c]:8.3g}" for c in range(4))
                print(f"    {mean_d[b]:8.2f} {int(count[b]):6d}   {cells}   (link 0, link 1)")
            print(
                f"    at pre-distance 0 (a line through the nearest {args.fit_bins} bins; 90% interval resampling "
                f"{'val' if name == 'val-train' else 'train'} tosses): unpredictable RMS per link, its square as a "
                "fraction of the engine's mean squared error"
            )
            for link in range(intercept.shape[0]):
                cells = [
                    f"{p} {intercept[link, c]:.3g} [{low[link, c]:.3g}, {high[link, c]:.3g}] "
                    f"({max(intercept[link, c], 0) ** 2 / engine_sq[link, c]:.0%})"
                    for c, p in enumerate(PARTS)
                ]
                print(f"      link {link}  " + "  ".join(cells))
            found[name] = {"at distance 0": intercept, "its 5% bound": low, "nearest bin": rms[0]}
        if args.oracle_noise:
            for label, rms in found[args.noise_pairs].items():
                noise = np.maximum(rms, 0.0)
                oracle_with_noise(args, dataset, meshes, split, rollouts, params, report, k, noise, label)


def oracle_with_noise(args, dataset, meshes, split, rollouts, params, report, k, rms, label) -> None:
    """The oracle first impact k frames after it, the recorded state there perturbed by an unpredictable part
    (isotropic Gaussian per link and part of RMS `rms` [K, 4]): the metric a perfect conditional mean would keep."""
    use, pre, post = impact_frames(split, meshes, dataset.floor_z, args, k)
    base = rollouts.rollout_context(make_context(split, dataset.dt, args.context_frames), params).poses[0]
    resets = [[] for _ in split.lengths]
    for n, frame in zip(use, post):
        resets[n] = [int(frame)]
    if label == "at distance 0":
        report(f"  oracle first impact k={k}", roll_with_resets(rollouts, params, split, base, resets))
    rng = np.random.default_rng(args.seed)
    sigma = rms / np.sqrt(3)  # [K, 4] per component
    h = heading(split.poses[use, pre])
    values = []
    for _ in range(args.draws):
        residual = rng.normal(size=(len(use),) + sigma.shape + (3,)) * sigma[..., None]
        poses, velocities = split.poses.copy(), split.velocities.copy()
        poses[use, post], velocities[use, post] = apply_residual(
            h, poses[use, post], velocities[use, post], residual.reshape(len(use), -1)
        )
        noisy = Split(poses=poses, lengths=split.lengths, velocities=velocities)
        predicted = roll_with_resets(rollouts, params, noisy, base, resets)
        values.append(score(split, predicted, dataset, args.context_frames))
    mean, spread = np.mean(values, axis=0), np.std(values, axis=0)
    print(
        f"    + unpredictable part, {args.noise_pairs} {label}: {mean[0]:.4f} widths / {mean[1]:.3f} rad "
        f"({args.draws} draws, std {spread[0]:.3f} / {spread[1]:.3f})",
        flush=True,
    )


def pose_noise(split: Split, context_frames: int) -> np.ndarray:
    """[K, 6] per link: position (m) and rotation (rad) components' median over tosses of the residual std
    (dof-corrected) of a quadratic fitted in time to the context poses (rotation: the rotation vector of each frame
    against the middle one)."""
    poses = split.poses[:, :context_frames]
    middle = poses[:, context_frames // 2 : context_frames // 2 + 1, :, 3:]
    turn = rotations.to_rotation_vector(rotations.multiply(poses[..., 3:], rotations.conjugate(middle)))
    values = np.concatenate([poses[..., :3], turn], axis=-1)  # [N, C, K, 6]
    t = np.arange(context_frames) - context_frames // 2
    design = np.stack([np.ones(context_frames), t, t**2], axis=1)
    hat = design @ np.linalg.pinv(design)
    residual = values - np.einsum("ij,njkc->nikc", hat, values)
    return np.median(np.sqrt((residual**2).sum(axis=1) / (context_frames - 3)), axis=0)


def perturbed_states(rng, poses, velocities, pose_sigma, velocity_sigma):
    """A state [M, K, 7] / [M, K, 6] with Gaussian noise: positions, rotation vectors (world frame), velocities."""
    shift = rng.normal(size=poses.shape[:-1] + (6,)) * pose_sigma
    turned = rotations.multiply(rotations.from_rotation_vector(shift[..., 3:]), poses[..., 3:])
    noisy = np.concatenate([poses[..., :3] + shift[..., :3], turned], axis=-1)
    return noisy, velocities + rng.normal(size=velocities.shape) * velocity_sigma


def squared_parts(h, poses, velocities, reference, k: int) -> np.ndarray:
    """[M, K, 4] squared distance per link and part between a state [M, K, 7] / [M, K, 6] and a reference
    simulation's frame k, in the heading frames h."""
    residual = state_residual(h, poses, velocities, reference.poses[0][:, k], reference.velocities[0][:, k])
    return (residual.reshape(len(h), -1, 4, 3) ** 2).sum(-1)


def sensitivity(args, dataset, meshes, train, split, context, rollouts, params, result) -> None:
    """Measurement 2: the engine's spread k frames after the impact from tracker-sized noise the frame before it."""
    pose_sigma = pose_noise(train, args.context_frames) * args.noise_scale
    velocity_sigma = velocity_noise(train, args.context_frames) * args.noise_scale
    print("pose noise per link [x y z (mm) rx ry rz (mrad)]:", np.round(1e3 * pose_sigma, 3).tolist())
    print("velocity noise per link [vx vy vz (m/s) wx wy wz (rad/s)]:", np.round(velocity_sigma, 3).tolist())
    ks = np.array(args.ks)
    simulated = Split(poses=result.poses[0], lengths=split.lengths, velocities=result.velocities[0])
    for source, states in (("the engine's rollout", simulated), ("the recording", split)):
        use, pre, _ = impact_frames(states, meshes, dataset.floor_z, args, int(ks.max()))
        poses0, velocities0 = states.poses[use, pre], states.velocities[use, pre]
        h = heading(poses0)
        rng = np.random.default_rng(args.seed)
        steps = int(ks.max()) + 1
        reference = rollouts.simulate(params, poses0, velocities0, steps)
        draws = []  # per draw, per k: [M, K, 4] squared distance from the unperturbed continuation
        for _ in range(args.draws):
            noisy = rollouts.simulate(
                params, *perturbed_states(rng, poses0, velocities0, pose_sigma, velocity_sigma), steps
            )
            draws.append([squared_parts(h, noisy.poses[0][:, k], noisy.velocities[0][:, k], reference, k) for k in ks])
        print(f"\nfrom {source}'s state the frame before its first impact ({len(use)} tosses, {args.draws} draws):")
        for n, k in enumerate(ks):
            spread = np.stack([d[n] for d in draws]).mean(axis=(0, 1))
            truth = split.poses[use, pre + 1 + k], split.velocities[use, pre + 1 + k]
            error = squared_parts(h, *truth, reference, k).mean(0)
            print(f"  k={k}: RMS spread of the draws about the unperturbed continuation (the engine's RMS error)")
            for link in range(spread.shape[0]):
                cells = [
                    f"{p} {np.sqrt(s):.3g} ({np.sqrt(e):.3g})" for p, s, e in zip(PARTS, spread[link], error[link])
                ]
                print(f"    link {link}  " + "  ".join(cells))
        if source != "the engine's rollout":
            continue
        # the same noise, the perturbed rollout carried to the end and scored against the unperturbed one
        rng, base = np.random.default_rng(args.seed), result.poses[0]
        values = []
        for _ in range(args.draws):
            noisy = Split(poses=base.copy(), lengths=split.lengths, velocities=result.velocities[0].copy())
            noisy.poses[use, pre], noisy.velocities[use, pre] = perturbed_states(
                rng, poses0, velocities0, pose_sigma, velocity_sigma
            )
            resets = [[] for _ in split.lengths]
            for n, frame in zip(use, pre):
                resets[n] = [int(frame)]
            rolled = roll_with_resets(rollouts, params, noisy, base, resets)
            values.append(score(Split(poses=base, lengths=split.lengths), rolled, dataset, args.context_frames))
        mean, std = np.mean(values, axis=0), np.std(values, axis=0)
        print(
            f"  perturbed the frame before the impact, carried to the end, against the unperturbed rollout: "
            f"{mean[0]:.4f} widths / {mean[1]:.3f} rad (draws' std {std[0]:.3f} / {std[1]:.3f})"
        )
        values = []  # the same pose and velocity noise at the context's last frame, for comparison
        for _ in range(args.draws):
            poses, velocities = context.poses.copy(), context.velocities.copy()
            poses[:, -1], velocities[:, -1] = perturbed_states(
                rng, poses[:, -1], velocities[:, -1], pose_sigma, velocity_sigma
            )
            rolled = rollouts.rollout_context(replace(context, poses=poses, velocities=velocities), params)
            values.append(
                score(Split(poses=base, lengths=split.lengths), rolled.poses[0], dataset, args.context_frames)
            )
        mean, std = np.mean(values, axis=0), np.std(values, axis=0)
        print(
            f"  the same pose and velocity noise at the context's last frame instead: {mean[0]:.4f} widths / "
            f"{mean[1]:.3f} rad (draws' std {std[0]:.3f} / {std[1]:.3f})"
        )


def quaternion_mean(quaternions: np.ndarray) -> np.ndarray:
    """[..., 4] the chordal mean of quaternions [D, ..., 4]: each sign-aligned with the first, summed, normalised."""
    signs = np.sign(np.einsum("d...i,...i->d...", quaternions, quaternions[0]))
    signs[signs == 0] = 1.0
    return rotations.normalize((signs[..., None] * quaternions).sum(axis=0))


def ensemble(args, dataset, split, context, rollouts, params, result, report) -> None:
    """Measurement 3: the per-frame mean of the chaos floor's perturbed-context rollouts, scored."""
    sigma = velocity_noise(dataset.split("train"), args.context_frames) * args.noise_scale
    rng = np.random.default_rng(args.seed)  # drawn as elbow_impact_ceiling.py's chaos floor draws them
    members = []
    for _ in range(args.ensemble):
        velocities = context.velocities.copy()
        velocities[:, -1] += rng.normal(size=velocities[:, -1].shape) * sigma
        members.append(rollouts.rollout_context(replace(context, velocities=velocities), params).poses[0])
    members = np.stack(members)  # [D, N, T, K, 7]
    scores = np.array([score(split, member, dataset, args.context_frames) for member in members])
    print(
        f"{'members, each alone':<32} {scores[:, 0].mean():.4f} widths / {scores[:, 1].mean():.3f} rad (std "
        f"{scores[:, 0].std():.3f} / {scores[:, 1].std():.3f}, best {scores[:, 0].min():.4f} / "
        f"{scores[:, 1].min():.3f})"
    )
    mean = np.concatenate([members[..., :3].mean(axis=0), quaternion_mean(members[..., 3:])], axis=-1)
    report(f"ensemble mean ({args.ensemble} members)", mean)
    t = np.arange(mean.shape[1])
    scored = (t >= args.context_frames) & (t[None] < split.lengths[:, None])  # [N, T]
    gap = joint_errors(mean, dataset.joints)[0].max(axis=-1)[scored]  # [S] m, the hinge anchors' distance
    own = joint_errors(members[0], dataset.joints)[0].max(axis=-1)[scored]
    metrics = compute_metrics(
        split.poses[:, : mean.shape[1]],
        mean,
        split.lengths,
        args.context_frames,
        [dataset.body_mesh(k) for k in range(dataset.n_bodies)],
        dataset.floor_z,
        joints=dataset.joints,
    )
    print(
        f"hinge anchors apart in the mean forecast: mean {1e3 * gap.mean():.1f} mm, median {1e3 * np.median(gap):.1f}, "
        f"95th percentile {1e3 * np.quantile(gap, 0.95):.1f}, max {1e3 * gap.max():.1f} (the metric's joint_gap_m "
        f"{1e3 * metrics.summary['joint_gap_m']:.1f} mm; one member alone: mean {1e3 * own.mean():.2f} mm)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", default=RUN, help="a SysID train run folder (fitted.json, .hydra/config.yaml)")
    parser.add_argument("--dataset", default="assets/contactnets_elbow")
    parser.add_argument("--limit", type=int, default=None, help="only the val split's first LIMIT tosses")
    parser.add_argument("--analogues", action="store_true", help="measurement 1: nearest pre-impact states")
    parser.add_argument("--oracle-noise", action="store_true", help="with --analogues: the oracle plus the nugget")
    parser.add_argument("--noise-pairs", default="val-train", choices=["val-train", "train-train"])
    parser.add_argument("--sensitivity", action="store_true", help="measurement 2: the engine's spread at impact")
    parser.add_argument("--ensemble", type=int, default=0, help="measurement 3: the mean of N perturbed rollouts")
    parser.add_argument("--ks", type=int, nargs="+", default=[2, 3, 4], help="frames after the impact")
    parser.add_argument(
        "--quantiles", type=float, nargs="+", default=[0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0], help="bin edges"
    )
    parser.add_argument("--fit-bins", type=int, default=3, help="the nearest bins the line to distance 0 runs through")
    parser.add_argument("--boots", type=int, default=200, help="resamples for the interval at distance 0")
    parser.add_argument("--margin", type=float, default=0.005, help="m: a vertex this near the floor touches it")
    parser.add_argument("--draws", type=int, default=8, help="perturbed draws (sensitivity, oracle noise)")
    parser.add_argument("--noise-scale", type=float, default=1.0, help="the measured noise times this")
    parser.add_argument("--context-frames", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not (args.analogues or args.sensitivity or args.ensemble):
        parser.error("name a measurement: --analogues, --sensitivity or --ensemble N")
    dataset, meshes, split, context, rollouts, params, report = prepare(args, "val")
    train = dataset.split("train")
    started = time.perf_counter()

    try:
        result = rollouts.rollout_context(context, params)
        report("baseline", result.poses[0])
        if args.analogues:
            analogues(args, dataset, meshes, train, split, rollouts, params, report)
        if args.sensitivity:
            sensitivity(args, dataset, meshes, train, split, context, rollouts, params, result)
        if args.ensemble:
            ensemble(args, dataset, split, context, rollouts, params, result, report)
    finally:
        rollouts.close()
    print(f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
