"""Model-free contact signatures from recorded poses: friction by slip direction, speed and place; spin, roll, bounce.

Free flight (diagnosis.free_flight) reads gravity and drag off the recordings with no simulator; in contact the same
can be done where one frame's motion isolates one law. Each measurement is a least-squares fit over the frames of a
split (the rows: diagnosis.contact_rows, from each body's per-frame force and geometry: diagnosis.contact_kinematics),
with percentile intervals from resampling tosses (the frames of a toss count together; diagnosis.contact_statistics),
and its evidence on val (confirmed on test) as in free flight: MEASURED, RULED_OUT or INCONCLUSIVE. Bodies on joints
are read through their tree's total momentum, while one of its bodies alone touches the floor (contact_kinematics).

Margins are calibrated on PyBullet datasets with nothing concealed (see each margin).
"""

from __future__ import annotations

import numpy as np

from contactbench.diagnosis.contact_rows import HELD_SPIN, split_rows
from contactbench.diagnosis.contact_statistics import (
    BOUNCE_CELL,
    FRICTION_CELL,
    MIN_TOSSES,
    anisotropy,
    cell_spread,
    coefficient,
    held_share,
    rolling_resistance,
    speed_change,
)
from contactbench.diagnosis.free_flight import INCONCLUSIVE, MEASURED, RULED_OUT, resample_weights, systems
from contactbench.scene import Recordings, Split

SPLITS = ("train", "val", "test")

# Practical margins, each above what PyBullet shows with nothing concealed (the val intervals of null datasets of
# every shape) and, where an effect shows there, below what the library's reference effects (strength 1) give; what
# the nulls and the effects gave: docs/results/calibration.md.
# - anisotropy amplitude a of mu(theta) = mu0 (1 + a cos 2(theta - axis)); 0.03 is a ratio of 1.06.
ANISOTROPY_MARGIN = 0.03
# - relative change of mu over the central 80% of the slip speeds.
SPEED_MARGIN = 0.05
# - spread of mu over floor cells, relative, debiased (a checkerboard's cells straddle tiles, so its spread reads low).
POSITION_MARGIN = 0.03
# - torsional and rolling resistance in metres (torque per unit load). Rolling's margin is higher: a viscous floor,
#   drag and spin damping resist a roll too.
SPIN_MARGIN = 0.003  # m
ROLLING_MARGIN = 0.005  # m
# - share of flat sliding frames whose spin is held below HELD_SPIN (torsional friction makes spin stick at zero, so
#   its kinetic steps all but vanish).
HELD_MARGIN = 0.4
# - bounce ratio (rebound / approach speed of the landing vertex): its change over the central 80% of approach
#   speeds (wide: PyBullet's own bounce depends on the impact speed), and its spread over floor cells. No effect of
#   the generator changes either.
BOUNCE_SPEED_MARGIN = 0.3
BOUNCE_POSITION_MARGIN = 0.15

# What each signature speaks to: a library effect (diagnosis.library) or physics the library does not list.
SPEAKS_TO = {
    "anisotropy": "anisotropic_friction",
    "speed": "outside the library: friction that depends on the slip speed (Stribeck, a viscous floor)",
    "position": "outside the library: friction that depends on where on the floor (patches, tiles)",
    "spin": "torsional_friction",
    "rolling": "rolling_friction",
    "bounce_speed": "outside the library: a restitution that depends on the impact speed",
    "bounce_position": "outside the library: a restitution that depends on where on the floor",
}


# How bodies on joints are read, per signature (contact_kinematics): said beside each finding on a hinged scene.
_BY_THE_TREE = (
    "Bodies on joints are read through their tree's total {what}, in which the joint's forces cancel, while one body "
    "of the tree alone touches the floor (the floor's whole force acts at its contact); frames where several bodies "
    "of a tree touch are left out, since how the load splits between them is not in the poses."
)
HINGED = {
    "anisotropy": _BY_THE_TREE.format(what="momentum"),
    "speed": _BY_THE_TREE.format(what="momentum"),
    "position": _BY_THE_TREE.format(what="momentum"),
    "spin": _BY_THE_TREE.format(what="momentum and angular momentum about its centre of mass"),
    "rolling": _BY_THE_TREE.format(what="momentum and angular momentum about its centre of mass"),
    "bounce_speed": (
        "A hinged body's landing counts after its whole tree flew for two frames, with it alone touching at landing; "
        "the landing vertex's rebound over its approach is read off that body's own motion, as a free body's."
    ),
}
HINGED["bounce_position"] = HINGED["bounce_speed"]


def measure_split(dataset: Recordings, split: Split, rng: np.random.Generator, bootstrap: int, confidence: float):
    """Every signature's statistic in one split (value, interval, counts); a signature with frames from fewer than
    MIN_TOSSES tosses gets counts only."""
    rows = split_rows(dataset, split)
    weights = resample_weights(split.n_trajectories, rng, bootstrap)
    width = float(dataset.widths().max())
    sliding, landing = rows["sliding"], rows["landing"]
    statistics = {
        "anisotropy": (sliding, lambda: anisotropy(sliding, weights, confidence)),
        "speed": (sliding, lambda: speed_change(sliding, weights, confidence, relative=True)),
        "position": (sliding, lambda: cell_spread(sliding, weights, confidence, FRICTION_CELL * width, True)),
        "spin": (rows["spin"], lambda: coefficient(rows["spin"], weights, confidence)),
        "rolling": (rows["rolling"], lambda: rolling_resistance(rows["rolling"], weights, confidence)),
        "bounce": (landing, lambda: coefficient(landing, weights, confidence)),
        "bounce_speed": (landing, lambda: speed_change(landing, weights, confidence, relative=False)),
        "bounce_position": (landing, lambda: cell_spread(landing, weights, confidence, BOUNCE_CELL * width, False)),
    }
    out = {}
    for name, (part, statistic) in statistics.items():
        tosses = len(np.unique(part.toss))
        out[name] = statistic() if tosses >= MIN_TOSSES else {"n_tosses": tosses, "n_frames": len(part.toss)}
    out["spin_held"] = held_share(rows["held"], weights, confidence)
    return out


# ---------------------------------------------------------------- evidence


def evidence(val: dict, test: dict, margin: float, two_sided: bool = True) -> tuple[str, bool]:
    """MEASURED: val's interval lies beyond the margin (on one side), and test confirms where it has an interval (its
    estimate beyond the margin on that side, its interval clear of zero); RULED_OUT: val's interval within the margin;
    else INCONCLUSIVE. Also whether test confirmed."""
    if "ci" not in val:
        return INCONCLUSIVE, False
    low, high = val["ci"]
    above, below = low > margin, two_sided and high < -margin
    if above or below:
        if "ci" not in test:
            return MEASURED, False
        if above:
            confirmed = bool(test["value"] > margin and test["ci"][0] > 0)
        else:
            confirmed = bool(test["value"] < -margin and test["ci"][1] < 0)
        return (MEASURED if confirmed else INCONCLUSIVE), confirmed
    # A debiased size far below zero is noise that swamps it: not ruled out.
    return (RULED_OUT if -margin < low and high < margin else INCONCLUSIVE), False


MARGINS = {
    "anisotropy": ANISOTROPY_MARGIN,
    "speed": SPEED_MARGIN,
    "position": POSITION_MARGIN,
    "spin": SPIN_MARGIN,
    "spin_held": HELD_MARGIN,
    "rolling": ROLLING_MARGIN,
    "bounce_speed": BOUNCE_SPEED_MARGIN,
    "bounce_position": BOUNCE_POSITION_MARGIN,
}
# Sizes that cannot be negative but for noise (amplitudes, spreads, shares): only their upper side is measured.
ONE_SIDED = ("anisotropy", "position", "spin_held", "bounce_position")


def measure(dataset: Recordings, rng: np.random.Generator, bootstrap: int = 1000, confidence: float = 0.95) -> dict:
    """The contact signatures per split and their evidence on val, confirmed on test: `signatures[name]` holds the
    evidence, the margin, what it speaks to and a sentence for the report; `evidence` maps library effects
    (anisotropic_friction, torsional_friction, rolling_friction) to MEASURED / RULED_OUT / INCONCLUSIVE. The spin
    evidence joins two statistics: the torsional friction read off kinetic steps, and the share of sliding frames
    whose spin is held at zero (strong torsional friction leaves hardly any kinetic steps). On a scene with bodies on
    joints each signature also says how they were read and what was left out (`hinged`, also in its sentence)."""
    splits = {
        name: measure_split(dataset, dataset.split(name), rng, bootstrap, confidence)
        for name in SPLITS
        if name in dataset.splits
    }
    val, test = splits.get("val", {}), splits.get("test", {})
    signatures = {}
    for name, margin in MARGINS.items():
        state, confirmed = evidence(val.get(name, {}), test.get(name, {}), margin, name not in ONE_SIDED)
        signatures[name] = {"evidence": state, "confirmed": confirmed, "margin": margin}
    rolling = signatures["rolling"]
    if rolling["evidence"] == MEASURED and val["rolling"]["beside_viscous_ci"][0] <= ROLLING_MARGIN:
        # it grows with the roll's speed: a force at the centre (a viscous floor, drag) or a spin damping, which
        # resist rolling about the contact too, rather than rolling friction
        rolling.update(evidence=INCONCLUSIVE, confirmed=False, viscous=True)
    kinetic, held = signatures.pop("spin"), signatures.pop("spin_held")
    # Either statistic may lack frames (few flat slides on many-faced bodies; few kinetic steps where strong
    # torsional friction holds the spin): one that rules it out then decides, unless the other is noisy.
    states = [
        found["evidence"] for found, name in ((kinetic, "spin"), (held, "spin_held")) if "ci" in val.get(name, {})
    ]
    if MEASURED in states:
        spin_state = MEASURED
    elif states and all(state == RULED_OUT for state in states):
        spin_state = RULED_OUT
    else:
        spin_state = INCONCLUSIVE
    signatures["spin"] = {
        "evidence": spin_state,
        "confirmed": kinetic["confirmed"] or held["confirmed"],
        "margin": SPIN_MARGIN,
        "held_margin": HELD_MARGIN,
        "kinetic_evidence": kinetic["evidence"],
        "held_evidence": held["evidence"],
    }
    hinged = any(len(tree) > 1 for tree in systems(dataset))
    for name, found in signatures.items():
        found["speaks_to"] = SPEAKS_TO[name]
        found["confidence"] = confidence
        found["sentence"] = SENTENCES[name](splits, found)
        if hinged:
            found["hinged"] = _hinged_note(name, splits)
            found["sentence"] += " " + found["hinged"]
    return {
        "confidence": confidence,
        "splits": splits,
        "signatures": signatures,
        "evidence": {
            "anisotropic_friction": signatures["anisotropy"]["evidence"],
            "torsional_friction": signatures["spin"]["evidence"],
            "rolling_friction": signatures["rolling"]["evidence"],
        },
    }


# ---------------------------------------------------------------- sentences


def _hinged_note(name: str, splits: dict) -> str:
    """How a signature reads bodies on joints, and the splits where that left too few tosses for an interval."""
    parts = ("spin", "spin_held") if name == "spin" else (name,)
    short = [split for split, found in splits.items() if not any("ci" in found.get(part, {}) for part in parts)]
    if not short:
        return HINGED[name]
    tosses = ", ".join(f"{split} {max(splits[split][part]['n_tosses'] for part in parts)}" for split in short)
    return f"{HINGED[name]} Too few tosses with such frames for an interval: {tosses} (of {MIN_TOSSES} needed)."


def _values(splits: dict, name: str, digits: int, unit: str = "") -> str:
    parts = []
    for split, found in splits.items():
        part = found.get(name, {})
        if "ci" in part:
            low, high = part["ci"]
            parts.append(f"{split} {part['value']:.{digits}f}{unit} [{low:.{digits}f}, {high:.{digits}f}]")
        else:
            parts.append(f"{split} too few ({part.get('n_tosses', 0)} tosses)")
    return ", ".join(parts)


def _ci(found: dict) -> str:
    return f"{found['confidence']:.0%} CI"


def _verdict(found: dict, what: str, margin: str) -> str:
    speaks = found["speaks_to"]
    about = f"library effect {speaks}" if "outside" not in speaks else speaks.split(": ", 1)[1]
    if found["evidence"] == MEASURED:
        tail = "confirmed on test" if found["confirmed"] else "test has too few frames to confirm"
        return f"{what} beyond {margin} (val), {tail}: evidence for {about}."
    if found["evidence"] == RULED_OUT:
        return f"{what} ruled out: val's interval lies within {margin} ({about})."
    return f"{what}: neither measured nor ruled out at {margin} (val, or not confirmed on test)."


def _anisotropy_sentence(splits: dict, found: dict) -> str:
    val = splits.get("val", {}).get("anisotropy", {})
    extra = (
        f"; on val mu0 {val['mu0']:.3f}, the largest friction along {val['axis_deg']:.0f} deg (max/min "
        f"{val['ratio']:.2f})"
        if "ci" in val
        else ""
    )
    return (
        f"Sliding friction against the slip direction, mu = mu0 (1 + A cos 2(theta - axis)), A debiased ({_ci(found)}, "
        f"flat sliding steps): {_values(splits, 'anisotropy', 3)}{extra}. "
        + _verdict(found, "An anisotropic floor friction", f"A = {ANISOTROPY_MARGIN}")
    )


def _speed_sentence(splits: dict, found: dict) -> str:
    return (
        "Sliding friction against slip speed, relative change of mu over the central 80% of speeds "
        f"({_ci(found)}): {_values(splits, 'speed', 3)}. "
        + _verdict(found, "A friction that changes with speed", f"{SPEED_MARGIN:.0%} of mu")
        + " (Air drag shows here too; free flight tells it apart.)"
    )


def _position_sentence(splits: dict, found: dict) -> str:
    return (
        f"Sliding friction against floor position, spread of mu over {FRICTION_CELL:g}-width cells relative to its "
        f"mean, debiased ({_ci(found)}): {_values(splits, 'position', 3)}. "
        + _verdict(found, "A friction that varies over the floor", f"{POSITION_MARGIN:.0%} of mu")
    )


def _spin_sentence(splits: dict, found: dict) -> str:
    head = (
        "Spin decay: torsional friction (spin torque per load, m) while pivoting on one vertex, where Coulomb "
        f"friction has no spin torque ({_ci(found)}): {_values(splits, 'spin', 4, ' m')}; share of flat sliding frames "
        f"whose spin is held below {HELD_SPIN} rad/s: {_values(splits, 'spin_held', 2)}. "
    )
    if found["evidence"] == MEASURED:
        tail = "confirmed on test" if found["confirmed"] else "test has too few frames to confirm"
        return (
            f"{head}A torsional friction: the torque beyond {SPIN_MARGIN * 1000:g} mm, or spin held in over "
            f"{HELD_MARGIN:.0%} of sliding frames (val), {tail}: evidence for library effect torsional_friction."
        )
    if found["evidence"] == RULED_OUT:
        return (
            f"{head}A torsional friction ruled out: val's torque within {SPIN_MARGIN * 1000:g} mm and spin held in "
            f"under {HELD_MARGIN:.0%} of sliding frames, where measured (library effect torsional_friction)."
        )
    return f"{head}A torsional friction: neither measured nor ruled out (val, or not confirmed on test)."


def _rolling_sentence(splits: dict, found: dict) -> str:
    head = (
        "Rolling decay: rolling resistance (torque against the roll per load about the touching edge or vertex, "
        f"m; {_ci(found)}): {_values(splits, 'rolling', 4, ' m')}. "
    )
    if found.get("viscous"):
        return (
            f"{head}It exceeds {ROLLING_MARGIN * 1000:g} mm but grows with the roll's speed: a force at the centre (a "
            "viscous floor, drag) or a spin damping, not rolling friction; inconclusive for rolling_friction."
        )
    return head + _verdict(found, "A rolling resistance", f"{ROLLING_MARGIN * 1000:g} mm")


def _bounce_speed_sentence(splits: dict, found: dict) -> str:
    return (
        f"Bounce ratio at landings (rebound / approach speed of the landing vertex; {_ci(found)}): "
        f"{_values(splits, 'bounce', 3)}; its change over the central 80% of approach speeds: "
        f"{_values(splits, 'bounce_speed', 3)}. "
        + _verdict(found, "A bounce that depends on the impact speed", f"{BOUNCE_SPEED_MARGIN:g}")
    )


def _bounce_position_sentence(splits: dict, found: dict) -> str:
    return (
        f"Bounce ratio against floor position, spread over {BOUNCE_CELL:g}-width cells, debiased "
        f"({_ci(found)}): {_values(splits, 'bounce_position', 3)}. "
        + _verdict(found, "A bounce that varies over the floor", f"{BOUNCE_POSITION_MARGIN:g}")
    )


SENTENCES = {
    "anisotropy": _anisotropy_sentence,
    "speed": _speed_sentence,
    "position": _position_sentence,
    "spin": _spin_sentence,
    "rolling": _rolling_sentence,
    "bounce_speed": _bounce_speed_sentence,
    "bounce_position": _bounce_position_sentence,
}
