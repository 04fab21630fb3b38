"""The diagnosis report's figures: the residual by phase, the signature of the named effects, a held-out trajectory,
the candidates against the margin."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from contactbench.diagnosis.phases import PHASES, label_phases
from contactbench.diagnosis.segments import COMPONENTS
from contactbench.evaluation.plotting import new_figure, save_figure
from contactbench.models.analytical import EngineContactModel
from contactbench.protocol import make_context


def phase_components(located: dict, path: Path) -> Path:
    cells = np.array([[located["cells"][f"{p}/{c}"] for c in COMPONENTS] for p in PHASES])
    errors = np.array([[located["cells_ci95"][f"{p}/{c}"] for c in COMPONENTS] for p in PHASES])  # [P, C, 2]
    figure = new_figure(figsize=(7, 3.6))
    axis = figure.subplots()
    width = 0.8 / len(COMPONENTS)
    for j, component in enumerate(COMPONENTS):
        x = np.arange(len(PHASES)) + j * width
        axis.bar(
            x,
            cells[:, j],
            width,
            label=component,
            yerr=[cells[:, j] - errors[:, j, 0], errors[:, j, 1] - cells[:, j]],
            capsize=2,
        )
    axis.set_xticks(np.arange(len(PHASES)) + 0.4 - width / 2, PHASES)
    axis.set_ylabel("share of squared residual")
    axis.set_title("Base simulator: residual by contact phase x component (val, 95% CI)")
    axis.legend(fontsize=7)
    return save_figure(figure, path)


def signature(arrays: dict, path: Path) -> Path | None:
    """Observed base residual against the change the winning effect makes (its signature), per residual entry."""
    final, steps = arrays["final"], arrays["steps"]
    if not final.effects:
        return None
    fit = steps.val_fit
    base_residuals = fit.residuals(arrays["base"], arrays["base_values"][None])[0].ravel()
    change = base_residuals - fit.residuals(final, arrays["final_values"][None])[0].ravel()
    rng = np.random.default_rng(0)
    shown = rng.choice(len(change), size=min(len(change), 20000), replace=False)
    figure = new_figure(figsize=(4.6, 4.2))
    axis = figure.subplots()
    axis.scatter(change[shown], base_residuals[shown], s=2, alpha=0.3)
    limit = np.percentile(np.abs(change), 99.5) * 1.2 or 1.0
    axis.plot([-limit, limit], [-limit, limit], color="k", lw=0.8)
    axis.set_xlim(-limit, limit)
    axis.set_ylim(-limit * 2, limit * 2)
    correlation = float(np.corrcoef(change, base_residuals)[0, 1])
    axis.set_xlabel(f"signature of {'+'.join(final.names)} (model change)")
    axis.set_ylabel("base residual")
    axis.set_title(f"residual vs signature, r = {correlation:.2f}")
    return save_figure(figure, path)


def trajectory(arrays: dict, path: Path) -> Path:
    """The held-out trajectory the augmented model improves most (the first if none), phases shaded."""
    steps = arrays["steps"]
    dataset = steps.dataset
    gain = arrays["before"]["pos_err"] - arrays["after"]["pos_err"]
    index = int(np.argmax(gain)) if arrays["final"].effects else 0
    test = dataset.split("test").select([index])
    context = make_context(test, dataset.dt, steps.context_frames)
    before, after = (
        EngineContactModel(name, engine=hypothesis.engine, parameters=hypothesis.contact_parameters(values)).rollout(
            dataset.scene, context
        )[0]
        for name, hypothesis, values in (
            ("base", arrays["base"], arrays["base_values"]),
            ("final", arrays["final"], arrays["final_values"]),
        )
    )
    phases = label_phases(dataset, test)[0, :, 0]
    length = int(test.lengths[0])
    time = np.arange(length) * dataset.dt
    figure = new_figure(figsize=(9, 3.4))
    axes = figure.subplots(1, 2)
    for axis, coordinate, label in ((axes[0], 0, "x (m)"), (axes[1], 2, "z (m)")):
        for phase, colour in zip(range(1, len(PHASES)), ("tab:red", "tab:orange", "tab:green", "tab:gray")):
            mask = phases[:length] == phase
            axis.fill_between(
                time,
                0,
                1,
                where=mask,
                transform=axis.get_xaxis_transform(),
                color=colour,
                alpha=0.15,
                label=PHASES[phase],
            )
        axis.plot(time, test.poses[0, :length, 0, coordinate], "k", label="recorded")
        axis.plot(time, before[:length, 0, coordinate], "--", label="base")
        axis.plot(time, after[:length, 0, coordinate], ":", label="augmented")
        axis.set_xlabel("t (s)")
        axis.set_ylabel(label)
    axes[0].legend(fontsize=6)
    figure.suptitle(f"held-out trajectory {index} (body 0)")
    return save_figure(figure, path)


def candidates(candidates: list[dict], margin: float, path: Path) -> Path | None:
    scored = [c for c in candidates if c.get("val_improvement") is not None]
    if not scored:
        return None
    figure = new_figure(figsize=(6, 0.4 * len(scored) + 1.4))
    axis = figure.subplots()
    labels = [f"{c['name']} (round {c['round']})" for c in scored]
    values = np.array([c["closes_of_base_loss"] for c in scored])
    low = np.array([c["closes_ci95"][0] for c in scored])
    high = np.array([c["closes_ci95"][1] for c in scored])
    axis.barh(
        labels,
        values,
        # a bootstrap interval of one or two held-out tosses can miss its own estimate by a rounding error
        xerr=[np.maximum(values - low, 0.0), np.maximum(high - values, 0.0)],
        capsize=3,
        color=["tab:green" if c["passes"] else "tab:gray" for c in scored],
    )
    axis.axvline(margin, color="k", ls="--", lw=0.8, label=f"margin {margin:.0%}")
    axis.set_xlabel("share of the base val loss closed (95% CI)")
    axis.legend(fontsize=7)
    return save_figure(figure, path)
