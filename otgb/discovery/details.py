"""report.md's "Details": how f_phi was named, the evidence against each alternative, the cross-checks, the library
search, the solves that diverged, the prior family and the pointwise errors against a known process."""

from __future__ import annotations

import math
from typing import Any

from otgb.discovery.families import CONSTANT, varies
from otgb.discovery.prior_text import distribution_text
from otgb.discovery.scores import STANDARD_ERRORS, clears
from otgb.discovery.variation import FIRST_SPREAD, SPREAD_DOUBLINGS
from otgb.discovery.verdict import undertrained_text

GAP_ROWS = {"f_p": "f_p alone", "greybox": "OT grey-box", "augmented": "augmented physics", "reference": "Reference"}


def cross_check_row(row: dict[str, Any]) -> str:
    """One strong candidate alone added to f_p: its coefficient, its lead over f_p alone, and the share of the gap it
    closes where that lead exceeds two standard errors."""
    below, error = row["below_f_p"], row["standard_error"]
    lead, closed = f"{below:.3g} ± {error:.2g}", f"{row['gap_closed']:.2f}" if clears(below, error) else "within noise"
    if not math.isfinite(row["gap_closed"]):
        lead = closed = "diverges"
    return f"| {code(row['feature'])} | d{row['component']}/dt | {row['coefficient']:.4g} | {lead} | {closed} |"


def naming_section(report: dict[str, Any]) -> list[str]:
    """How f_phi was named: its regression per component, each named term's regression figures, then the evidence,
    the cross-checks, the search, the diverged solves and the prior family."""
    lines = ["## What the learned correction is", ""]
    if report.get("evidence_on"):
        lines += [
            f"Every held-out score below that decides between models is computed on {report['evidence_on']}: 'the "
            "validation part' is read as those trajectories, each scored by fits that did not see it "
            "(docs/discovery.md, Cross-fitted evidence).",
            "",
        ]
    if report["correction_share"] is not None:
        lines.append(
            f"The grey-box's correction f_phi has {report['correction_share']:.3g} times the size (RMS) of f_p "
            "along its trajectories."
        )
        lines.append("")
    for s in report["regression"]:
        lines.append(
            f"- d{s['component']}/dt: selected {', '.join(s['selected']) or 'nothing'}; "
            f"R^2 of f_phi explained {s['explained_r2']:.3f}; "
            f"library condition number {s['condition_number']:.3g}" + _confusable(s["confusable_pairs"])
        )
    lines += regression_table(report["terms"])
    if report["undertrained"]:
        u = report["undertrained"]
        said = undertrained_text(
            u["difference"], u["standard_error"], u["validation_trajectories"], u["greybox_heldout_energy"],
            u["f_p_heldout_energy"],
        )  # fmt: skip
        lines.append(f"\n**The OT grey-box's correction is not used:** it {said}.")
    lines += diverged_section(report["diverged"])
    lines += evidence_section(report)
    lines += forms_section(report.get("forms"))
    lines += [
        "",
        "### Cross-check: each strong candidate alone added to f_p",
        "",
        "Held-out energy on the validation part, lower is better; the share of f_p alone's that a candidate removes is "
        "given where it lies below f_p alone's by more than two standard errors (else it is noise: a share of a gap the "
        "validation part cannot see).",
        "",
        "| feature | on | fitted coefficient | below f_p alone's held-out energy (± standard error) | share of the gap closed |",
        "|---|---|---|---|---|",
    ]
    lines += [cross_check_row(row) for row in report["cross_check"]]
    lines += search_section(report)
    lines += theta_search_section(report.get("theta_search"))
    if report["dropped_by_heldout_check"]:
        lines.append("")
        dropped = ", ".join(f"`{d['feature']}`" for d in report["dropped_by_heldout_check"])
        lines.append(f"Dropped (no held-out gain beside the kept terms; swapped for a named term: the evidence above): {dropped}")
    lines += family_section(report)
    return lines + [""]


def regression_table(terms: list[dict[str, Any]]) -> list[str]:
    """Each named term beside f_phi's regression: its inclusion probability, f_phi's slope and its share of f_phi."""
    if not terms:
        return []
    lines = [
        "",
        "| term | feature | on | coefficient | 95 % interval | inclusion | f_phi's slope [95 %] "
        "| share of f_phi (R^2) | distribution |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for t in terms:
        interval = f"[{t['interval'][0]:.4g}, {t['interval'][1]:.4g}]" if t["interval"] else "-"
        inclusion = f"{t['inclusion_probability']:.2f}" if t["inclusion_probability"] is not None else "-"
        share = f"{t['r2_share']:.3f}" if t["r2_share"] is not None else "-"
        slope = (
            f"{t['regression_coefficient']:.4g} [{t['regression_interval'][0]:.4g}, {t['regression_interval'][1]:.4g}]"
            if t["regression_coefficient"] is not None
            else "-"
        )
        lines.append(
            f"| {t['name']} | {code(t['feature'])} | d{t['component']}/dt | {t['coefficient']:.4g} | {interval} "
            f"| {inclusion} | {slope} | {share} | {distribution_text(t['distribution'])} |"
        )
    return lines


def diverged_section(diverged: list[dict[str, Any]]) -> list[str]:
    """The solves that diverged, per step and model."""
    if not diverged:
        return []
    lines = [
        "",
        "### Solves that diverged",
        "",
        "A fit or a score whose solve diverged counts its model as infinitely worse in that step; a verification leaves "
        "the diverged trajectories out. **named**: the model this report names.",
        "",
        "| step | f_p plus | diverged trajectories | first inputs |",
        "|---|---|---|---|",
    ]
    for d in diverged:
        terms = ", ".join(code(t) for t in d["terms"]) or "nothing"
        terms += " (**named**)" if d.get("named") else ""
        if d.get("coefficients"):
            terms += f" with {', '.join(d['coefficients'])}"
        first = ", ".join(f"{v:.4g}" for v in d["first_inputs"]) if d["first_inputs"] else "-"
        lines.append(f"| {d['what']} | {terms} | {d['diverged']} of {d['of']} | {first} |")
    return lines


def evidence_section(report: dict[str, Any]) -> list[str]:
    """Each kept term against its alternatives on the validation measurements, and the ambiguous ones."""
    if not report["evidence"]:
        return []
    lines = [
        "",
        "### Evidence: each named term against its alternatives (validation measurements, which no fit saw)",
        "",
        "| named | swapped for | its coefficient | held-out energy, swapped minus named | standard errors |",
        "|---|---|---|---|---|",
    ]
    for e in report["evidence"]:
        if math.isfinite(e["difference"]):
            difference, errors = f"{e['difference']:+.3g} ± {e['standard_error']:.2g}", f"{e['standard_errors']:+.1f}"
        else:
            difference, errors = "the swapped model diverges", "-"
        lines.append(
            f"| {code(e['feature'])} | {e['alternative_name']} ({code(e['alternative'])}) | {e['alternative_coefficient']:.4g} "
            f"| {difference} | {errors} |"
        )
    lines.append(
        "\nEach named term is weighed against the strong candidates on its component that closed most of the gap alone, "
        "the terms it moves with along the grey-box's solves (the confusable pairs above) and, for a friction, Coulomb "
        "friction. "
        "Positive: the named term fits better. Within ±2 standard errors the measurements cannot tell the two apart."
    )
    for a in report["added_by_evidence"]:
        errors = a["difference"] / a["standard_error"] if a["standard_error"] > 0 else float("inf")
        lines.append(
            f"\nAdded by the evidence: {code(a['feature'])} on d{a['component']}/dt lowers the held-out energy by "
            f"{a['difference']:.3g} ± {a['standard_error']:.2g} ({errors:.1f} standard errors); its coefficient "
            f"{a['coefficient']:.4g}, 95 % interval [{a['interval'][0]:.4g}, {a['interval'][1]:.4g}] (training part)."
        )
    for a in report["ambiguous"]:
        others = ", ".join(f"{code(x['alternative'])} ({x['standard_errors']:+.1f} SE)" for x in a["alternatives"])
        lines.append(f"\n**Ambiguous:** the measurements cannot tell {code(a['feature'])} from {others}.")
    return lines


def family_section(report: dict[str, Any]) -> list[str]:
    """The prior family: each family's score and difference to the chosen one, and the spread the data allow."""
    if not report["family"]:
        return []
    differences = report["family_difference"]
    scores = ", ".join(
        f"{k} {v:.4g} ({differences[k]['difference']:+.2g} ± {differences[k]['standard_error']:.2g})"
        for k, v in report["family_training_discrepancy"].items()
        if k != report["family"]
    )
    lines = [
        "",
        f"Prior family of the coefficients: **{report['family']}** (energy discrepancy to the training measurements "
        f"{report['family_training_discrepancy'][report['family']]:.4g}; the others, and their difference to it: {scores}; "
        "a richer family is chosen only if lower by more than two standard errors).",
    ]
    alike = [
        k
        for k, d in differences.items()
        if k not in (CONSTANT, report["family"]) and d["difference"] <= STANDARD_ERRORS * d["standard_error"]
    ]
    noise = report.get("run", {}).get("measurement_noise") or 0.0
    if noise > 0:
        lines.append(f"Every simulation compared with the measurements carried white noise of sd {noise:.4g} (theirs).")
    elif varies(report["family"]):
        lines.append(
            "The simulations carried no measurement noise (data.measurement_noise 0): noise in the measurements "
            "widens their spread at every time, as a coefficient that varies between trajectories would. Where the "
            "measurements are noisy, read this family as a varying coefficient or measurement noise, or give their "
            "noise's sd as data.measurement_noise (docs/discovery.md, measurement noise)."
        )
    if varies(report["family"]) and alike:
        lines.append(
            f"The training measurements cannot tell the {report['family']} family from {' or '.join(alike)} (within two "
            "standard errors): that the coefficient varies is shown, the shape of its distribution is not."
        )
    for family in report["family_stopped_short"]:
        lines.append(
            f"The {family} fit scored no better than the constant, which its family contains (zero width): "
            "it was taken at zero width."
        )
    for family, reason in report.get("family_rejected", {}).items():
        lines.append(f"The {family} family scored best on the training part but is not kept: {reason}.")
    for t in report["terms"]:
        if t["spread_interval"]:
            low, high = t["spread_interval"]
            spread = f"95 % interval [{low:.4g}, {high:.4g}]"
            lines.append(f"Spread of {code(t['feature'])} (half-width or standard deviation): {spread}.")
        elif not varies(report["family"]):
            lines.append(f"{code(t['feature'])} is constant; " + _spread_bound(t["excluded_spread"]))
    return lines


def _spread_bound(bound: float | None) -> str:
    if bound is None:
        return f"the data cannot exclude a spread up to {FIRST_SPREAD * 2**SPREAD_DOUBLINGS:.3g} times its size."
    return (
        f"a spread wider than {bound:.3g} (half-width; standard deviation if only the normal family is tried) "
        "is excluded by the data (two standard errors)."
    )


def search_section(report: dict) -> list[str]:
    """The library search's path (when f_phi's route left the gap open), and which route named the terms."""
    if not report["search"]:
        return []
    lines = ["", "### Library search: every local candidate fitted together, then the best subset of each size", ""]
    if report.get("search_reason"):
        lines += [f"It ran because {report['search_reason']}.", ""]
    lines += path_table(report["search"], report.get("search_unsupported"))
    return lines + ["", f"Terms named by: **{report['route']}**." if report["route"] else "Nothing kept."]


def theta_search_section(theta: dict | None) -> list[str]:
    """The search on terms that scale with theta, where it ran: why, its path and whether its model replaced the
    answer's terms."""
    if not theta:
        return []
    lines = ["", "### Terms that scale with theta", "", f"Searched because {theta['reason']}.", ""]
    lines += path_table(theta["path"], theta.get("unsupported")) if theta["path"] else ["The search fitted no model."]
    if theta["kept"]:
        kept = ", ".join(f"{code(t['feature'])} on d{t['component']}/dt" for t in theta["kept"])
        better = f"{theta['below_answer']:.3g} ± {theta['standard_error']:.2g}"
        return lines + ["", f"Its model, {kept}, replaces the answer's terms: it fits the validation part better by {better}."]
    return lines + ["", "No model of the search fits the validation part better than the answer by two standard errors."]


def path_table(steps: list[dict], unsupported: list[dict] | None) -> list[str]:
    """A library search's models, each on the validation part against f_p alone, and the terms it dropped."""
    first = steps[0]
    lines = [
        f"Held-out energy: on {first['validation_trajectories']} held-out trajectories, lower is better; a model is "
        "kept only where it is below f_p alone's by more than two standard errors of the difference.",
        "",
        "| terms | residual of g (relative RMS) | held-out energy | below f_p alone's (± standard error) |",
        "|---|---|---|---|",
        f"| f_p alone | - | {first['heldout_energy'] + first['below_f_p']:.4g} | - |",
    ]
    for step in steps:
        terms = ", ".join(f"{code(t['feature'])} on d{t['component']}/dt" for t in step["terms"])
        below = f"{step['below_f_p']:.3g} ± {step['standard_error']:.2g}"
        lines.append(f"| {terms} | {step['g_residual']:.3f} | {step['heldout_energy']:.4g} | {below} |")
    if unsupported:
        dropped = "; ".join(
            f"{code(u['feature'])} on d{u['component']}/dt (coefficient {u['coefficient']:.3g}, interval "
            f"[{u['interval'][0]:.3g}, {u['interval'][1]:.3g}])"
            for u in unsupported
        )
        lines += ["", f"Dropped from the search's model, their coefficients' 95 % intervals holding zero: {dropped}."]
    return lines


def forms_section(forms: dict | None) -> list[str]:
    """The parametric forms weighed against the kept linear terms: why, each one's fit and whether it was taken."""
    if not forms:
        return []
    lines = ["", "### Parametric forms in place of linear terms", "", f"Weighed because {forms['reason']}.", ""]
    lines += ["| form | replaces | parameters (95 % interval) | better than the linear terms by (± standard error) | taken |"]
    lines += ["|---|---|---|---|---|"]
    for fit in forms["tried"]:
        parameters = ", ".join(
            f"{p['name']} = {p['value']:.4g}" + (f" [{p['interval'][0]:.4g}, {p['interval'][1]:.4g}]" if p["interval"] else "")
            for p in fit["parameters"]
        )  # fmt: skip
        replaced = ", ".join(code(f) for f in fit["replaces"]) or "-"
        taken = "yes" if fit["feature"] == forms["adopted"] else "alike" if fit["feature"] in forms.get("alike", []) else "no"
        why = f": {fit['refused']}" if fit["refused"] else ""
        better = f"{fit['difference']:.3g} ± {fit['standard_error']:.2g}"
        lines.append(f"| {code(fit['form'])} | {replaced} | {parameters} | {better} | {taken}{why} |")
    return lines


def pointwise_section(pointwise: dict) -> list[str]:
    """ABS ERR / N-RMSE against a known DGP, over the training horizon and the next one (extrapolation)."""
    if not pointwise:
        return []
    lines = ["", "## Pointwise errors against the known process", ""]
    lines += ["On the test inputs (the second horizon is extrapolation):", ""]
    lines += ["| model | ABS ERR | N-RMSE | ABS ERR, 2nd horizon | N-RMSE, 2nd horizon |", "|---|---|---|---|---|"]
    for key, label in GAP_ROWS.items():
        if key in pointwise:
            e = pointwise[key]
            lines.append(
                f"| {label} | {e['abs_err_horizon']:.4g} | {e['nrmse_horizon']:.4g} | {e['abs_err_twice_horizon']:.4g} "
                f"| {e['nrmse_twice_horizon']:.4g} |"
            )
    return lines


def code(text: str) -> str:
    """Inline code that survives a Markdown table cell (its pipes escaped)."""
    return "`" + text.replace("|", "\\|") + "`"


def _confusable(pairs: list[dict]) -> str:
    if not pairs:
        return ""
    return "; confusable pairs: " + ", ".join(f"{p['a']} ~ {p['b']} ({p['correlation']:.3f})" for p in pairs)
