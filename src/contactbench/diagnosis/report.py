"""diagnosis.json and report.md with the plots a person reads in a minute."""

from __future__ import annotations

from pathlib import Path

from contactbench import atomic
from contactbench.diagnosis import contact_law_report
from contactbench.diagnosis import figures as figures_of
from contactbench.diagnosis.phases import PHASES


def write_diagnosis(document: dict, arrays: dict, out_dir: Path) -> Path:
    out_dir = Path(out_dir)
    figures = out_dir / "figures"
    try:
        drawn = [
            figures_of.phase_components(document["located"], figures / "residual_by_phase.png"),
            figures_of.signature(arrays, figures / "signature.png"),
            figures_of.trajectory(arrays, figures / "heldout_trajectory.png"),
            figures_of.candidates(
                document["candidates"], document["decision_rule"]["margin"], figures / "candidates.png"
            ),
        ]
    finally:
        arrays["steps"].close()
    atomic.write_json(out_dir / "diagnosis.json", document)
    atomic.write_text(out_dir / "report.md", _markdown(document, [path for path in drawn if path is not None]))
    return out_dir / "report.md"


def budget_sentence(document: dict) -> str:
    """The budget the verdict was reached at; at smoke, plainly that the verdict is not conclusive."""
    name, budget = document.get("budget_name", "custom"), document["budget"]
    size = (
        f"{budget['fit_trajectories']} train tosses fitted, {budget['val_trajectories']} val tosses judging, "
        f"{budget['base_evaluations']} base evaluations, at most {budget['max_effects']} effect(s) from "
        f"{budget['front_runners']} front-runner(s), {budget['bootstrap']} bootstrap resamples"
    )
    if not document.get("conclusive", True):
        return (
            f"Budget: {name} ({size}). This checks that the pipeline runs, nothing more: the verdict is NOT "
            f"conclusive; run budget=quick (the default) or budget=paper before reading anything into it."
        )
    return f"Budget: {name} ({size})."


def console_paragraph(document: dict, report: Path) -> str:
    """What diagnose.py says last: the verdict, what it rests on, and where the report is."""
    conclusive = "" if document.get("conclusive", True) else " (not conclusive)"
    return f"Verdict: {document['verdict']}{conclusive}. {summary_sentence(document)} Report: {report}"


def summary_sentence(document: dict) -> str:
    text = contact_law_report.short(document.get("contact_law")) + _verdict_sentence(document)
    falling = document.get("free_flight") or {}
    found = []
    if falling.get("confirmed"):
        found.append(
            f"bodies in free flight fall at {falling['splits']['test']['along_gravity']:.3f} m/s² on test (train "
            f"{falling['scale']:.4f} × meta.gravity)"
        )
    if falling.get("drag_confirmed"):
        test = falling["splits"]["test"]
        found.append(
            f"a drag slows them (k = {test['drag_per_m']:.3f}/m on test, 95% CI {test['drag_ci95'][0]:.3f} to "
            f"{test['drag_ci95'][1]:.3f})"
        )
    if document["verdict"] in ("none", "unconfirmed") and found:
        text += (
            " Nothing the simulator models is confirmed on the held-out tosses; what is confirmed is model-free: "
            f"{' and '.join(found)}; see the free-flight section."
        )
    if not document.get("conclusive", True):
        text = f"At budget={document.get('budget_name')} (not conclusive): {text}"
    return text


def _verdict_sentence(document: dict) -> str:
    held = document["heldout"]
    where = document["located"]["where"]
    if document["verdict"] == "confounded":
        rivals = [c for c in document["candidates"] if c.get("confounded_with") is not None]
        listed = "; ".join(
            f"{c['name']} closes {c['val_improvement']:.1%} (95% CI {c['ci95'][0]:.1%} to {c['ci95'][1]:.1%})"
            for c in rivals
        )
        return (
            f"Confounded: {' or '.join(document['confounded'])}. Each passes the rule on val, and paired trajectory "
            f"by trajectory neither is significantly better than the other ({listed}): these recordings cannot tell "
            "which is missing, so none is named."
        )
    if document["verdict"] == "unexplained":
        return _unexplained_sentence(document) + _unconfirmed_note(document)
    if document["verdict"] == "none":
        return (
            f"No candidate effect improved the fit significantly and by the margin; the remaining mismatch lives in "
            f"{where} (held-out position error {held['base']['pos_err']:.4f} widths).{_predictor_note(document)}"
        )
    names = " and ".join(f"{e['name']} ({e['physics']})" for e in document["effects"])
    held_text = (
        f"held-out position error {held['base']['pos_err']:.4f} -> {held['augmented']['pos_err']:.4f} widths "
        f"({held['improvement']:.1%}, 95% CI {held['ci95'][0]:.1%} to {held['ci95'][1]:.1%}){_short_text(held)}"
    )
    if not held["confirmed"]:
        return (
            f"Val data point to {names}, but the held-out test does not confirm it ({held_text}): treat it as "
            f"unproven; the mismatch lives in {document['located']['where']}.{_drag_caveat(document)}"
            f"{_predictor_note(document)}"
        )
    return (
        f"Missing: {names}; modelling it changed the {held_text}; what remains lives in "
        f"{document['located_after']['where']}.{_drag_caveat(document)}"
    )


def _drag_caveat(document: dict) -> str:
    """Where a named drag is not the size free flight measures (diagnosis.simulated_drag)."""
    for effect in document["effects"]:
        check = effect.get("against_free_flight")
        if check and not check["consistent"]:
            return (
                f" But the named drag is not the one free flight measures: {_drag_comparison(check)}: read the fitted "
                "density as a knob fitted to the simulator's loss, not as a measurement of the air."
            )
    return ""


def _against_free_flight(check: dict | None) -> str:
    if check is None:
        return ""
    return f"; {_drag_comparison(check)}: " + ("consistent" if check["consistent"] else "not consistent")


def _drag_comparison(check: dict) -> str:
    low, high = check["simulated_range"]
    measured_low, measured_high = check["measured_ci95"]
    return (
        f"at the fitted density the simulated body decelerates at k = {check['simulated_k_per_m']:.3f}/m ({low:.3f} "
        f"to {high:.3f} over orientations), {check['ratio']:.1f}x the k = {check['measured_k_per_m']:.3f}/m (95% CI "
        f"{measured_low:.3f} to {measured_high:.3f}) measured model-free on val"
    )


def _short_text(held: dict) -> str:
    short = held.get("short_horizon")
    if short is None:
        return ""
    return (
        f"; short-horizon loss on test {short['improvement']:.1%} lower (95% CI {short['ci'][0]:.1%} to "
        f"{short['ci'][1]:.1%}; reported, not proof)"
    )


def _predictor_note(document: dict) -> str:
    found = document.get("predictable")
    return f" {found['sentence']}" if found else ""


def _unconfirmed_note(document: dict) -> str:
    if not document["effects"]:
        return ""
    held = document["heldout"]
    names = " and ".join(e["name"] for e in document["effects"])
    return (
        f" Val data pointed to {names}, an unconfirmed candidate: its held-out full rollouts changed by "
        f"{held['improvement']:.1%} (95% CI {held['ci95'][0]:.1%} to {held['ci95'][1]:.1%})."
    )


def _unexplained_sentence(document: dict) -> str:
    found = document["unexplained"]
    if found["by"] == "predictor":
        return document["predictable"]["sentence"]
    if found["by"] == "contact_signatures":
        signatures = document["contact_signatures"]["signatures"]
        measured = " ".join(signatures[name]["sentence"] for name in found["depends_on"])
        return "Something is missing that no name modelled in MuJoCo improves, measured model-free: " + measured
    found = document["open_world"]
    located, held = found["located"], found["heldout"]
    phase_share = located["phase_shares"][located["phase"]]
    return (
        f"Something the library does not list is missing: no effect passed, but a sparse correction of "
        f"{len(found['terms'])} terms closes {found['val_improvement']:.1%} of the val loss (95% CI "
        f"{found['ci95'][0]:.1%} to {found['ci95'][1]:.1%}); {phase_share:.0%} of that in {located['phase']} frames, "
        f"mostly in {located['output']}; on held-out test segments it closes {held['improvement']:.1%} (95% CI "
        f"{held['ci95'][0]:.1%} to {held['ci95'][1]:.1%}){'' if held['confirmed'] else ', not confirmed'}. "
        "See the open-world terms for what it depends on."
    )


def _free_flight_note(airborne: dict | None) -> str:
    if airborne is None:
        return ""
    return f"; in free flight {_free_flight(airborne)}"


def _free_flight(airborne: dict) -> str:
    low, high = airborne["ci95"]
    return (
        f"{airborne['improvement']:.3f} [{low:.3f}, {high:.3f}] there, "
        f"removing {airborne['removed_per_segment']:.3f} of the round's mean loss per segment"
    )


def _refit_control_note(candidate: dict) -> str:
    control = candidate.get("refit_control")
    if control is None or control["passes"]:
        return ""
    return (
        f" (against the model without it refitted from its values: {control['val_improvement']:.3f}, 95% CI "
        f"{control['ci95'][0]:.3f} to {control['ci95'][1]:.3f}: the gain was the refit, not the effect)"
    )


def _special_case_note(candidate: dict) -> str:
    special = candidate.get("no_better_than")
    return f" (no better than its special case {special})" if special else ""


def _contact_lines(found: dict | None) -> list[str]:
    if not found:
        return []
    lines = ["## Model-free in contact (diagnosis.contact_signatures)", ""]
    lines += [
        f"- {name} ({signature['speaks_to']}): **{signature['evidence']}**. {signature['sentence']}"
        for name, signature in found["signatures"].items()
    ]
    return [*lines, ""]


def _predictor_lines(found: dict | None) -> list[str]:
    if not found:
        return []
    shares = ", ".join(f"{phase} {share:.0%}" for phase, share in found["phase_shares"].items())
    dependence = ", ".join(f"{group} {share:.0%}" for group, share in found["dependence"].items())
    return [
        "## Is what the base misses predictable? (a flexible correction, diagnosis.predictable)",
        "",
        found["sentence"],
        "",
        f"Where it closes the val loss: {shares}. What its gain depends on (share lost when permuted; `constant`: "
        f"share kept with every group permuted): {dependence}.",
        "",
    ]


def _open_world_lines(found: dict | None) -> list[str]:
    if not found:
        return []
    lines = [
        "## Open world (a sparse correction outside the library)",
        "",
        "Generalized accelerations of each body, world frame, gated to one contact phase and proportional to one "
        "candidate dependence (diagnosis.open_world); fitted on train, judged on val by the same rule.",
        "",
    ]
    if not found["terms"]:
        return lines + ["No term improved the train BIC.", ""]
    lines += [
        f"Val: closes {found['val_improvement']:.1%} (95% CI {found['ci95'][0]:.1%} to {found['ci95'][1]:.1%}), "
        f"dBIC {found['delta_bic']:.0f}, located in {found['located']['phase']} frames (margin there "
        f"{found['margin']:.0%}): {'passes' if found['passes'] else 'does not pass'}.",
        "",
        "| output | phase | depends on | coefficient |",
        "|---|---|---|---|",
        *[f"| {t['output']} | {t['phase']} | {t['depends_on']} | {t['coefficient']:.4g} |" for t in found["terms"]],
        "",
    ]
    return lines


def _markdown(document: dict, figures: list[Path]) -> str:
    held, rule = document["heldout"], document["decision_rule"]
    lines = [
        "# Diagnosis",
        "",
        f"Verdict: **{document['verdict']}**{'' if document.get('conclusive', True) else ' (not conclusive)'}. "
        + summary_sentence(document),
        "",
        budget_sentence(document),
        "",
        *contact_law_report.lines(
            document.get("contact_law"), document.get("naming_base", "mujoco"), document.get("seconds", {})
        ),
        "## First, model-free: free flight",
        "",
        document["free_flight"]["sentence"],
        "",
        document["velocities"]["sentence"],
        "",
        *_free_flight_table(document["free_flight"]),
        *_contact_lines(document.get("contact_signatures")),
        "## Held-out (test, full rollouts from the context frames)",
        "",
        "| model | position error (widths) | rotation error (rad) |",
        "|---|---|---|",
        f"| base | {held['base']['pos_err']:.4f} | {held['base']['rot_err_rad']:.4f} |",
        f"| augmented | {held['augmented']['pos_err']:.4f} | {held['augmented']['rot_err_rad']:.4f} |",
        "",
        f"Improvement {held['improvement']:.1%} (95% CI {held['ci95'][0]:.1%} to {held['ci95'][1]:.1%}, paired "
        f"bootstrap over {held['n_trajectories']} test trajectories){_short_text(held)}. A name is confirmed where "
        f"the full rollouts improve (95% interval above zero): {'yes' if held['confirmed'] else 'no'}.",
        "",
        "## Effects",
        "",
    ]
    lines += [
        f"- `{e['name']}` ({e['mujoco']}): "
        + ", ".join(f"{k} = {v:.4g}" for k, v in e["parameters"].items())
        + _against_free_flight(e.get("against_free_flight"))
        for e in document["effects"]
    ] or ["- none"]
    lines += [
        f"- `{g['name']}` given the others: improvement {g['val_improvement']:.3f} (95% CI {g['ci95'][0]:.3f} to "
        f"{g['ci95'][1]:.3f}){_free_flight_note(g.get('airborne'))}, "
        f"{'kept' if g['passes'] else 'dropped as a passenger'}"
        for g in document.get("given_the_others", [])
    ]
    lines += [
        f"- `{e['name']}` given the others on test (full rollouts): {e['improvement']:.1%} (95% CI {e['ci95'][0]:.1%} "
        f"to {e['ci95'][1]:.1%}), {'kept' if e['kept'] else 'dropped: it does not improve the held-out tosses'}"
        for e in held.get("each_effect", [])
    ]
    lines += [
        "",
        "## Candidates (val)",
        "",
        "| round | effect | improvement over its round's model | 95% CI | share of the base loss closed | "
        "in free flight (later rounds, measured effects) | dBIC | "
        "passes |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in document["candidates"]:
        if c.get("val_improvement") is None:
            continue
        airborne = c.get("airborne")
        flying = _free_flight(airborne) if airborne else "–"
        by_flight = c["passes"] and c["round"] > 1 and c["val_improvement"] < rule["later_margin"]
        lines.append(
            f"| {c['round']} | {c['name']} | {c['val_improvement']:.3f} | [{c['ci95'][0]:.3f}, {c['ci95'][1]:.3f}] | "
            f"{c['closes_of_base_loss']:.3f} | {flying} | "
            f"{c['delta_bic']:.0f} | {'yes' if c['passes'] else 'no'}{' (chosen)' if c.get('chosen') else ''}"
            f"{' (margin: measured in free flight)' if c['passes'] and c.get('measured_model_free') else ''}"
            f"{' (significant in free flight)' if c['passes'] and c['ci95'][0] <= 0 else ''}"
            f"{' (margin: its gain in free flight)' if by_flight and not c.get('measured_model_free') else ''}"
            f"{' (ruled out model-free)' if c.get('ruled_out_model_free') else ''}"
            f"{' (fitted below its resolution: not this physics)' if c.get('negligible') else ''}"
            f"{_special_case_note(c)}{_refit_control_note(c)} |"
        )
    lines += ["", *_open_world_lines(document.get("open_world"))]
    lines += _predictor_lines(document.get("predictable"))
    located = document["located"]
    lines += [
        "",
        "## Where the base simulator misses (val, squared short-horizon residual)",
        "",
        "| phase | share | 95% CI | share of segments | above noise floor |",
        "|---|---|---|---|---|",
    ]
    for p in PHASES:
        ci = located["phase_shares_ci95"][p]
        lines.append(
            f"| {p} | {located['phase_shares'][p]:.3f} | [{ci[0]:.3f}, {ci[1]:.3f}] | "
            f"{located['segment_shares'][p]:.3f} | {'yes' if located['above_noise_floor'][p] else 'no'} |"
        )
    lines += ["", *[f"![{path.stem}](figures/{path.name})" for path in figures], ""]
    lines += [
        "## The rule",
        "",
        f"{rule['rule']}. Margins: {rule['margin']:.0%} (first round and the open-world correction), "
        f"{rule['later_margin']:.0%} (later rounds).",
        "",
    ]
    return "\n".join(lines)


def _free_flight_table(found: dict) -> list[str]:
    lines = [
        "| split | tosses | free-flight frames | fall c: x, y, z (m/s²) | c along gravity, 95% CI | drag k (1/m), "
        "95% CI |",
        "|---|---|---|---|---|---|",
    ]
    for name, part in found["splits"].items():
        if "acceleration" in part:
            ci, drag_ci = part["along_gravity_ci95"], part["drag_ci95"]
            lines.append(
                f"| {name} | {part['n_trajectories']} | {part['n_frames']} | "
                f"{', '.join(f'{a:.3f}' for a in part['acceleration'])} | "
                f"{part['along_gravity']:.3f} [{ci[0]:.3f}, {ci[1]:.3f}] | "
                f"{part['drag_per_m']:.3f} [{drag_ci[0]:.3f}, {drag_ci[1]:.3f}] |"
            )
    return lines + [""]
