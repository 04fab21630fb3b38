"""The contact-law section of the diagnosis report (diagnosis.contact_law's document)."""

from __future__ import annotations

from contactbench.diagnosis.contact_law import fit_seconds_key


def _parameters(parameters: dict) -> str:
    return ", ".join(
        f"{name} {value:.3g}" if isinstance(value, float) else f"{name} {value}" for name, value in parameters.items()
    )


def _against(law: dict) -> str:
    against = law.get("against_best")
    if against is None:
        return "best on val"
    val, full = against["val"], against["full_rollouts"]
    return (
        f"best closes {val['improvement']:.1%} ({val['ci95'][0]:.1%} to {val['ci95'][1]:.1%}) on val, "
        f"{against['test']['improvement']:.1%} on test; full rollouts {full['pos_improvement']:+.1%} "
        f"({full['ci95'][0]:.1%} to {full['ci95'][1]:.1%}){' (confirmed)' if against['confirmed'] else ''}"
    )


def lines(section: dict | None, naming_base: str, seconds: dict) -> list[str]:
    if section is None:
        return []
    out = [
        "## The contact law first (diagnosis.contact_law)",
        "",
        f"Best on val: **{section['best']}**. {section['finding']}.",
        "",
        "| contact law | fitted parameters | loss train / val / test | test full rollouts: widths / rad | fit (s) "
        "| against the best |",
        "|---|---|---|---|---|---|",
    ]
    for law in section["laws"]:
        full = law["full_rollouts"]
        fitted = seconds.get(fit_seconds_key(law["law"]), seconds.get("base_fit_s", 0.0))
        out.append(
            f"| {law['law']} | {_parameters(law['parameters'])} | {law['train_loss']:.5f} / {law['val_loss']:.5f} / "
            f"{law['test_loss']:.5f} | {full['pos_err']:.4f} / {full['rot_err_rad']:.4f} | {fitted:.0f} | "
            f"{_against(law)} |"
        )
    out.append("")
    for law in section["laws"]:
        against = law.get("against_best")
        if against is None:
            continue
        shares = against["val"]["by_phase"]
        listed = ", ".join(
            f"{phase} {100 * share['share']:.1f} ({100 * share['ci95'][0]:.1f} to {100 * share['ci95'][1]:.1f})"
            for phase, share in shares.items()
        )
        out.append(f"- Where {section['best']} beats {law['law']} (points of its val loss, by phase): {listed}.")
    out += [f"- {skipped['engine']} skipped: {skipped['reason']}" for skipped in section["skipped"]]
    out += [
        "",
        f"Every law is fitted on the same robust short-horizon loss ({section['budget']['law_evaluations']} "
        f"global-search evaluations and least squares on {section['budget']['law_trajectories']} train tosses per "
        "engine and contact option; MuJoCo is the diagnosis' own base fit, with its impedance), chosen on val, "
        "and confirmed on test where both the short-horizon loss and the full rollouts' position error improve "
        "(95% intervals above zero). Rolling and spinning friction are library effects, in no engine's base.",
        "",
    ]
    if naming_base != section["best"]:
        out += [
            f"The effects below are named on {naming_base}: "
            f"{section.get('naming_base_why') or section['best'] + ' models no library effect in this scene'}.",
            "",
        ]
    if section.get("not_modelled_on_naming_base"):
        out += [f"Not modelled on {naming_base}: {', '.join(section['not_modelled_on_naming_base'])}.", ""]
    return out


def short(section: dict | None) -> str:
    """One sentence: the best law, and what it closes of each other law's loss where the test confirms it."""
    if section is None:
        return ""
    confirmed = [
        f"{law['against_best']['val']['improvement']:.0%} of {law['law']}'s"
        for law in section["laws"]
        if law.get("against_best", {}).get("confirmed")
    ]
    beats = f": it closes {', '.join(confirmed)} val loss, confirmed on test" if confirmed else ""
    return f"The contact law that fits best is {section['best']}{beats}. "
