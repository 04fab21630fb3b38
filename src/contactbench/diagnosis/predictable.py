"""Whether a flexible correction of the fitted simulator predicts held-out residuals better than on null data.

Before the diagnosis says `none` (nothing is missing) it must show that what the fitted base simulator leaves is not
predictable from the recorded states. A small MLP maps each recorded state a segment passes through (its phase, the
velocity and its direction, the slip of the vertices on the floor, the spin, the impact speed of the lowest vertex,
height and orientation, the place on the floor) to a generalized acceleration per body, world frame; integrated over
the segment's frames as in diagnosis.open_world (frame j moves by dt^2 sum_{i<j} (j - i) a(x_i)), it corrects the
base simulator's short-horizon residual. Four members, each stopped early on its own quarter of the train tosses and
fitted on the rest, are averaged (fixed seeds, one thread: deterministic). On val and on test: the per-trajectory
robust loss the diagnosis scores with (ResidualFit.robust, trajectory_losses) before and after the correction, gain =
1 - after / before, with a bootstrap interval over trajectories (decision.bootstrap_ratio).

Two engines never agree exactly, so the correction gains on every dataset, nulls included: most of it at impacts and
along the contact normal (MuJoCo's soft contact and impact laws), and on the shapes that tip over edges along the floor
too. A single bound on the whole gain, high enough for the nulls, let most concealed effects through unnoticed. So what
is judged is where and on what the gain rests (STATISTICS): each part of the correction alone (free flight, impacts, the
contact normal, the rest of contact); the gain each group of recorded quantities carries, lost when that group is
shuffled among the states of the same phase (permutation importance); the gain lost when every state is turned about the
vertical and its correction turned back (a homogeneous floor under vertical gravity has no preferred heading); and the
gain left with every group shuffled (a constant per phase). Each has its own bound, the largest null interval plus a
margin (NULL_GAIN_BOUNDS, from benchmarks/predictable_calibration.py); the correction `passes` where a statistic's val
and test intervals both lie above its bound (how many effects and nulls pass: docs/results/calibration.md). Contact
feedback is left out, as in the open world: the correction says that something is missing, where and on what, not what a
MuJoCo model of it would be.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from contactbench.diagnosis.decision import bootstrap_ratio
from contactbench.diagnosis.phases import FREE, IMPACT, PHASES, REST, ROLLING, SLIDING
from contactbench.diagnosis.predictable_correction import Correction, Settings, corrected, integrate, train
from contactbench.diagnosis.predictable_states import GROUPS, Inputs, States, inputs, turn

if TYPE_CHECKING:
    from contactbench.diagnosis.library import Hypothesis
    from contactbench.diagnosis.state import Diagnosis

# Parts of the correction, judged each against its own null bound: the accelerations at the states of some phases,
# on some outputs (0-2: linear x, y, z; 3-5: angular).
PARTS = {
    "free": ((FREE,), (0, 1, 2, 3, 4, 5)),
    "impact": ((IMPACT,), (0, 1, 2, 3, 4, 5)),
    "contact_normal": ((SLIDING, ROLLING, REST), (2,)),
    "contact_tangential": ((SLIDING, ROLLING, REST), (0, 1, 3, 4, 5)),
}
# What is judged against nulls: each part alone, the gain each feature group carries, and the gain left with every
# group shuffled (a constant per phase).
# Besides the groups: "heading", the gain lost when every state is turned about the vertical by a random angle and
# its correction turned back. A homogeneous floor under vertical gravity has no preferred heading, so a correction
# that needs the world's heading (a wind, a floor whose friction differs between x and y) gains more than one that
# turns with the state (friction along the slip, a Coriolis force); on nulls turning costs nothing (it even helps).
DEPENDENCES = (*GROUPS, "heading", "constant")
STATISTICS = (*PARTS, *DEPENDENCES)
# The bound each statistic must pass, on val and on test (the lower end of the 95% interval above it), before the
# correction counts as gaining more than with nothing missing, for each base the correction is fitted on (the law named
# on, Hypothesis.law; "mujoco" is the diagnosis' own MuJoCo base): the largest upper end of that
# statistic's val and test intervals over the calibration's null datasets (nothing concealed; quick budget, Settings()
# as below), plus NULL_MARGIN. Measured by benchmarks/predictable_calibration.py with each base fitted as the diagnosis
# fits it; a change of a base's fit, of the features or of Settings needs a new calibration. The nulls, and which of
# them set each bound: docs/results/calibration.md. A base with no calibration of its own is judged against the
# largest bound of any base (null_gain_bounds). Impacts and the contact normal get the highest bounds because the
# engines' impact laws and soft contacts differ with nothing concealed; the floor position the lowest, since a
# homogeneous floor leaves nothing to read from the place.
NULL_MARGIN = 0.01  # of the base loss: beyond the null intervals' own width, room for shapes not measured
NULL_GAIN_BOUNDS = {
    "mujoco": {
        "free": 0.025,
        "impact": 0.136,
        "contact_normal": 0.088,
        "contact_tangential": 0.077,
        "direction": 0.123,
        "speed": 0.060,
        "spin": 0.054,
        "impact_speed": 0.035,
        "height_orientation": 0.030,
        "floor_position": 0.013,
        "heading": 0.019,
        "constant": 0.082,
    },
    "drake": {
        "free": 0.030,
        "impact": 0.180,
        "contact_normal": 0.071,
        "contact_tangential": 0.078,
        "direction": 0.111,
        "speed": 0.056,
        "spin": 0.093,
        "impact_speed": 0.095,
        "height_orientation": 0.054,
        "floor_position": 0.014,
        "heading": 0.016,
        "constant": 0.018,
    },
    "bullet (rigid contact)": {
        "free": 0.017,
        "impact": 0.044,
        "contact_normal": 0.101,
        "contact_tangential": 0.049,
        "direction": 0.041,
        "speed": 0.047,
        "spin": 0.033,
        "impact_speed": 0.015,
        "height_orientation": 0.019,
        "floor_position": 0.014,
        "heading": 0.017,
        "constant": 0.089,
    },
    "bullet (compliant contact)": {
        "free": 0.021,
        "impact": 0.079,
        "contact_normal": 0.095,
        "contact_tangential": 0.035,
        "direction": 0.030,
        "speed": 0.024,
        "spin": 0.028,
        "impact_speed": 0.016,
        "height_orientation": 0.021,
        "floor_position": 0.013,
        "heading": 0.013,
        "constant": 0.101,
    },
}


def null_gain_bounds(label: str) -> dict[str, float]:
    """The null bounds of a base (its label), or, for a base never calibrated, each statistic's largest bound over the
    calibrated bases: a correction of an uncalibrated base must gain more than any calibrated base gains on nulls."""
    if label in NULL_GAIN_BOUNDS:
        return dict(NULL_GAIN_BOUNDS[label])
    return {name: max(bounds[name] for bounds in NULL_GAIN_BOUNDS.values()) for name in STATISTICS}


STATISTIC_WORDS = {
    "free": "in free flight",
    "impact": "at impacts",
    "contact_normal": "along the floor normal in contact",
    "contact_tangential": "along the floor and in rotation in contact",
    "direction": "on the direction of motion and slip",
    "speed": "on the speed",
    "spin": "on the spin",
    "impact_speed": "on the impact speed",
    "height_orientation": "on the height and orientation",
    "floor_position": "on the position on the floor",
    "heading": "on the heading in the world (which way along the floor)",
    "constant": "as a constant per phase",
}


def part_mask(states: States, part: str) -> np.ndarray:
    """[M, L, K, 6] where a part of the correction (PARTS) acts: its phases' states, its outputs."""
    phases, outputs = PARTS[part]
    return np.isin(states.phase, phases)[..., None] & np.isin(np.arange(6), outputs)


def gain(split_inputs: Inputs, residual_change: np.ndarray) -> float:
    """1 - after / before of the split's mean per-trajectory robust loss."""
    before = split_inputs.losses(split_inputs.residuals)
    after = split_inputs.losses(corrected(split_inputs.residuals, residual_change))
    return float(1 - after.mean() / before.mean())


def phase_shares(correction: Correction, val: Inputs) -> dict[str, float]:
    """Share of the val loss the correction closes that its accelerations at the states of each phase close alone
    (a phase whose part makes the loss worse counts nothing)."""
    return shares(
        {
            p: gain(val, correction.change(val.features, (val.states.phase == i)[..., None]))
            for i, p in enumerate(PHASES)
        }
    )


def cut(
    correction: Correction, split_inputs: Inputs, name: str, rng: np.random.Generator, mask: np.ndarray | None = None
) -> np.ndarray:
    """The correction's change of the residuals with one dependence (DEPENDENCES) cut: the group shuffled among the
    states of the same phase (States.permuted), or, for "heading", every state turned about the vertical by a random
    angle and its acceleration turned back."""
    if name != "heading":
        return correction.change(split_inputs.states.permuted(name, rng).features(), mask)
    angles = rng.uniform(0.0, 2 * np.pi, size=split_inputs.states.phase.shape)
    accelerations = correction.accelerations(split_inputs.states.turned(angles).features())
    for axes in (slice(0, 2), slice(3, 5)):  # linear and angular, along the floor
        accelerations[..., axes] = turn(accelerations[..., axes], -angles)
    if mask is not None:
        accelerations = accelerations * mask
    return integrate(correction.integration, accelerations)


def carried(
    correction: Correction, val: Inputs, name: str, settings: Settings, mask: np.ndarray | None = None
) -> float:
    """The val gain a dependence carries: lost when it is cut (for "constant": kept with every group shuffled); of the
    accelerations where `mask` is True only, if given. Mean over `settings.permutations` cuts."""
    rng = np.random.default_rng(settings.seed)
    kept = float(np.mean([gain(val, cut(correction, val, name, rng, mask)) for _ in range(settings.permutations)]))
    return kept if name == "constant" else gain(val, correction.change(val.features, mask)) - kept


def shares(values: dict[str, float]) -> dict[str, float]:
    """Non-negative values as shares of their sum (all 0 where nothing is positive)."""
    clipped = {key: max(value, 0.0) for key, value in values.items()}
    total = sum(clipped.values())
    return {key: value / total if total > 0 else 0.0 for key, value in clipped.items()}


def excess(record: dict, name: str) -> float:
    """How far a statistic's lower interval end, the smaller of val's and test's, lies above its null bound (the
    record's `null_gain_bounds`)."""
    lowest = min(record[split]["statistics"][name]["ci95"][0] for split in ("val", "test"))
    return lowest - record["null_gain_bounds"][name]


def located(record: dict, correction: Correction, val: Inputs, settings: Settings) -> tuple[str, str, dict]:
    """Where (phase) and on what (group) the correction gains beyond nulls, and that group's gain by phase (shares).

    Where a group passes: the group furthest beyond its bound (the gain the engines' own differences leave, the
    direction of slip on an octahedron, is not what the excess depends on). Where only a part passes: the group that
    carries most of that part's gain. Where a part passes, the phase is that part's (of a contact part, the contact
    phase it closes most in), else where the group's gain acts most. Where nothing passes: the phase closing most and
    the group carrying most of the whole gain, to describe, not to decide."""
    groups = DEPENDENCES
    passing = [name for name in record["beyond_nulls"] if name in groups]
    parts = sorted((name for name in record["beyond_nulls"] if name in PARTS), key=lambda name: -excess(record, name))
    if passing:
        group = max(passing, key=lambda name: excess(record, name))
    elif parts:
        mask = part_mask(val.states, parts[0])
        group = max(groups, key=lambda name: carried(correction, val, name, settings, mask))
    else:
        group = max(record["dependence"], key=record["dependence"].get)
    by_phase = shares(
        {
            p: carried(correction, val, group, settings, (val.states.phase == index)[..., None])
            for index, p in enumerate(PHASES)
        }
    )
    if parts:
        phase = max((PHASES[p] for p in PARTS[parts[0]][0]), key=lambda p: record["phase_shares"][p])
    elif passing:
        phase = max(by_phase, key=by_phase.get)
    else:
        phase = max(record["phase_shares"], key=record["phase_shares"].get)
    return phase, group, by_phase


def judged(correction: Correction, split_inputs: Inputs, draws: int, confidence: float, settings: Settings) -> dict:
    """The correction's gain on one split (1 - after / before of the mean per-trajectory robust loss) with a bootstrap
    interval over trajectories, and the same for every statistic of STATISTICS: each part of the correction alone, the
    gain each dependence carries (lost when it is cut, cut(): the mean of `settings.permutations` cuts), and what is
    left with every group shuffled."""
    rng = np.random.default_rng(settings.seed)
    residuals, states = split_inputs.residuals, split_inputs.states
    before = split_inputs.losses(residuals)

    def after(change: np.ndarray) -> np.ndarray:
        return split_inputs.losses(corrected(residuals, change))

    full = after(correction.change(split_inputs.features))
    point, ci = bootstrap_ratio(before, full, draws, rng, confidence)
    statistics = {}
    for name in STATISTICS:
        if name in PARTS:
            other = after(correction.change(split_inputs.features, part_mask(states, name)))
        else:
            shuffled = np.mean(
                [after(cut(correction, split_inputs, name, rng)) for _ in range(settings.permutations)], axis=0
            )
            # a group's gain, (after shuffling - after) / before, is 1 - mean(other) / mean(before) for this other
            other = shuffled if name == "constant" else before - shuffled + full
        gained, interval = bootstrap_ratio(before, other, draws, rng, confidence)
        statistics[name] = {"gain": gained, "ci95": interval}
    return {"n_trajectories": int(split_inputs.n_trajectories), "gain": point, "ci95": ci, "statistics": statistics}


def check(steps: Diagnosis, hypothesis: Hypothesis, values: np.ndarray, settings: Settings = Settings()) -> dict:
    """The correction of a fitted hypothesis (usually the base simulator): fitted on train, its gain on val and test
    with 95% intervals (whole, by part, by feature group), where it acts, what it depends on, whether it gains more
    than on null data (`passes`), and a sentence for the report. The record:

    - val, test: gain and ci95 of the whole correction, and `statistics` (STATISTICS: gain, ci95 each);
    - beyond_nulls: the statistics above their null bounds (of the hypothesis' base: null_gain_bounds) on val
      and test; passes: any;
    - phase, depends_on, depends_on_by_phase: where and on what (located());
    - phase_shares: share of the closed val loss by the phase of the states where the correction acts;
    - dependence: per group, its gain on val as a share of the whole (above 1 where shuffled states make the
      correction worse than none); "constant": the share kept with every group shuffled;
    - training, null_gain_bounds, sentence.

    Uses its own random generators (settings.seed), not steps.rng: running the check changes none of the pipeline's
    draws. Seconds on one core at the quick budget."""
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a few thousand small rows: a second thread costs more than it saves on shared cores
    try:
        dataset = steps.dataset
        valid = steps.train_split.valid_mask()
        origin = steps.train_split.poses[..., :2][valid].reshape(-1, 2).mean(axis=0)
        train_inputs = inputs(dataset, steps.train_split, steps.train_fit, hypothesis, values, origin)
        correction, training = train(train_inputs, dataset.dt, settings)
        test_split, test_fit = steps.test_segments()
        val = inputs(dataset, steps.val_split, steps.val_fit, hypothesis, values, origin)
        test = inputs(dataset, test_split, test_fit, hypothesis, values, origin)
        draws, confidence = steps.budget.bootstrap, steps.decision.confidence
        record: dict = {
            "training": training,
            "val": judged(correction, val, draws, confidence, settings),
            "test": judged(correction, test, draws, confidence, settings),
            "phase_shares": phase_shares(correction, val),
        }
        full = record["val"]["gain"]
        record["dependence"] = {
            group: max(record["val"]["statistics"][group]["gain"] / full, 0.0) if full > 0 else 0.0
            for group in DEPENDENCES
        }
        record["null_gain_bounds"] = null_gain_bounds(hypothesis.law)
        record["beyond_nulls"] = beyond_nulls(record)
        record["passes"] = bool(record["beyond_nulls"])
        record["phase"], record["depends_on"], record["depends_on_by_phase"] = located(
            record, correction, val, settings
        )
        record["sentence"] = sentence(record)
        return record
    finally:
        torch.set_num_threads(torch_threads)


def beyond_nulls(record: dict) -> list[str]:
    """The statistics in which the correction gains more than on any null: both the val and the test interval above
    the statistic's bound."""
    return [name for name in record["null_gain_bounds"] if excess(record, name) > 0]


def sentence(record: dict) -> str:
    """One line for the report: how much the correction closes on test, and, where that is more than on nulls, where
    and on what."""
    test = record["test"]
    head = (
        f"A flexible correction of the fitted simulator closes {test['gain']:.0%} of its short-horizon test loss "
        f"[{test['ci95'][0]:.0%}, {test['ci95'][1]:.0%}]"
    )
    if not record["beyond_nulls"]:
        return head + ", no more than on null data: nothing predictable is missing."
    phase, group = record["phase"], record["depends_on"]
    share = f"{record['dependence'][group]:.0%} of its gain"
    what = (
        f"it is mostly a constant per phase ({share} kept with every recorded quantity shuffled)"
        if group == "constant"
        else f"it depends most {STATISTIC_WORDS[group]} ({share} lost without it)"
    )
    return (
        f"{head}, more than on null data ({', '.join(STATISTIC_WORDS[name] for name in record['beyond_nulls'])}): "
        f"most of it at {phase} states, and {what}."
    )


def calibration_table(results: dict[str, dict]) -> str:
    """A markdown table of check records by dataset name (benchmarks/predictable_calibration.py): each gain as val /
    test, with the lower ends of their 95% intervals."""

    def pair(val: dict, test: dict) -> str:
        return f"{val['gain']:.3f} ({val['ci95'][0]:.3f}) / {test['gain']:.3f} ({test['ci95'][0]:.3f})"

    lines = [
        "| dataset | whole | " + " | ".join(STATISTICS) + " | phase | top dependence | beyond nulls | s |",
        "|---" * (7 + len(STATISTICS)) + "|",
    ]
    for name, record in results.items():
        val, test = record["val"], record["test"]
        cells = " | ".join(pair(val["statistics"][s], test["statistics"][s]) for s in STATISTICS)
        lines.append(
            f"| {name} | {pair(val, test)} | {cells} "
            f"| {record['phase']} {record['phase_shares'][record['phase']]:.0%} "
            f"| {record['depends_on']} {record['dependence'][record['depends_on']]:.0%} "
            f"| {', '.join(record['beyond_nulls']) or '-'} | {record.get('check_s', float('nan')):.1f} |"
        )
    return "\n".join(lines)
