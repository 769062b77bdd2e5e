"""The discovery's outputs: ``report.json``, ``report.md`` with its figures, ``augmented.yaml``."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import yaml

from otgb.analysis.components import to_json
from otgb.analysis.figures import close, components_figure, disagreement_figure, distribution_figure, save
from otgb.discovery.library import fixed_in_space, implausible
from otgb.discovery.locate import DisagreementMap
from otgb.discovery.refine import centre, term_names
from otgb.discovery.variation import FIRST_SPREAD, SPREAD_DOUBLINGS
from otgb.discovery.workflow import Discovery, c2st_tells_apart, term_name, undertrained_text
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel
from otgb.physics.priors import Prior

GAP_ROWS = {"f_p": "f_p alone", "greybox": "OT grey-box", "augmented": "augmented physics", "reference": "Reference"}


def prior_dict(prior: Prior) -> dict[str, Any]:
    """A prior as a config entry (class_path / init_args)."""
    return {"class_path": f"otgb.physics.{type(prior).__name__}", "init_args": dict(prior.init_args)}


def distribution(prior: Prior) -> dict[str, Any] | None:
    """``null`` for a constant coefficient, else the prior's kind and parameters."""
    if prior.is_constant:
        return None
    return {"kind": type(prior).__name__.lower(), **prior.init_args}


def distribution_text(distribution: dict[str, Any] | None) -> str:
    """A coefficient's distribution (:func:`distribution`) as a person reads it: "constant", "U(low, high)",
    "N(mean, std)" or "one of a, b"."""
    if distribution is None:
        return "constant"
    kind = distribution["kind"]
    if kind == "uniform":
        return f"U({distribution['low']:.4g}, {distribution['high']:.4g})"
    if kind == "normal":
        return f"N({distribution['mean']:.4g}, {distribution['std']:.4g})"
    if kind == "choice":
        return "one of " + ", ".join(f"{v:.4g}" for v in distribution["values"])
    return json.dumps(distribution)


OUTSIDE_THE_LIBRARY = (
    "what f_p lacks may lie outside the candidate library (a forcing that depends on time or on position, an input the "
    "model does not have): write it as a term of your own and compare again (docs/own-physics.md)"
)


def outside_the_library(result: Discovery, physics: PhysicsModel) -> str:
    """:data:`OUTSIDE_THE_LIBRARY`; on a field whose library held no term fixed in space, also how to offer them."""
    names = getattr(physics, "coordinate_names", ())
    if not names or any(fixed_in_space(f, physics) for s in result.selections for f in s.inclusion):
        return OUTSIDE_THE_LIBRARY
    offered = f"{names[0]} and its powers" if len(names) == 1 else f"{' and '.join(names)} and their powers and products"
    return f"{OUTSIDE_THE_LIBRARY}; for one fixed in space (a heater, a sink), --discover.position_degree 2 adds {offered}"


OUTCOMES = ("gap closed", "found, not exactly", "named, not confirmed", "partly found", "nothing found", "nothing detected")


def outcome(result: Discovery) -> str:
    """Which of :data:`OUTCOMES` the verdict is (``report.json``'s ``outcome``): named terms are confirmed only where the
    augmented physics is nearer to the test part than f_p alone beyond chance (:func:`closer_on_test`), else "named,
    not confirmed"; "partly found" names the terms that came closest, not the missing effect itself."""
    if not result.before.any_significant:
        return "nothing detected"
    if not result.found:
        return "nothing found"
    if not closer_on_test(result):
        return "named, not confirmed"
    if closed_on_test(result):
        return "gap closed"
    return "found, not exactly" if distributions_agree(result) else "partly found"


def verdict(result: Discovery, physics: PhysicsModel) -> list[str]:
    """The verdict in parts, the answer first: one of :data:`OUTCOMES` (:func:`outcome`) with its numbers; then how
    strongly the measurements prefer each named term over its closest alternative, and the flags of implausible
    terms. ``report.json``'s ``verdict`` joins them with "; "."""
    kind = outcome(result)
    if kind == "nothing detected":
        return ["no missing effect detected: " + result.sentence_before]
    if kind == "nothing found":
        why = unscored_search(result) or "no candidate term fits the validation part better than f_p alone by two standard errors"
        return [
            f"no missing effect found in the library: the measurements differ from f_p ({result.sentence_before}), but {why}",
            *closest_unkept(result),
            outside_the_library(result, physics),
            *undertrained_note(result, "and the library search named nothing"),
            *low_power(result),
        ]
    ambiguous: dict[tuple[str, str], list] = {}
    for c in sorted(result.evidence, key=lambda c: c.standard_errors):  # those that fit better than the named term first
        if c.ambiguous and math.isfinite(c.difference):
            ambiguous.setdefault((c.replaced.feature, c.replaced.component), []).append(c)
    names = ", ".join(
        f"{term_name(c, centre(p), physics)} ({c.feature} on d{c.component}/dt)"
        + _or_alike(ambiguous.get((c.feature, c.component)), physics)
        for c, p in _terms(result)
    )
    removes, closes = ("removes", "closes") if len(_terms(result)) == 1 else ("remove", "close")
    blind = test_part_blind(result) if kind == "named, not confirmed" and closed_on_test(result) else None
    if blind:
        answer = [
            f"missing effect named, not confirmed: {names}, but the {len(result.draws['f_p'])} test trajectories cannot "
            f"tell even f_p from the measurements ({blind}), nor the augmented physics as nearer to them than f_p "
            f"({closer_clause(result)}), so their agreeing with the augmented physics confirms nothing: more "
            "measurements are needed to confirm it"
        ]
    elif kind == "named, not confirmed":
        test = result.closer
        versus = (
            f"energy distance {test.augmented:.3g} against f_p's {test.f_p:.3g}, from {test.augmented_draws} and "
            f"{test.f_p_draws} draws; half the test measurements against the other half: {test.floor:.3g}; "
            if test
            else ""
        )
        answer = [
            f"missing effect named, not confirmed: {names} fit the validation part better than f_p alone, but on the "
            f"{tested(result)} test trajectories, which no fit saw, the augmented physics is not significantly nearer "
            f"to the measurements than f_p alone ({versus}{closer_clause(result)})",
            result.sentence_after,
            outside_the_library(result, physics),
        ]
    elif kind == "gap closed":
        answer = [
            f"missing effect found, the gap is closed as far as the test part can tell: {names} {removes} "
            f"{share_removed(result)}, and no test tells the augmented physics from them",
            result.sentence_after,
        ]
    elif kind == "found, not exactly":  # the distributions agree, the recorded inputs do not
        answer = [
            f"missing effect found, not exactly: {names} {removes} {share_removed(result)} and the distribution tests "
            "see no difference on the test part, but solved on its recorded inputs the augmented physics misses the "
            "measurements by more than their noise: the coefficients (fitted to distributions) or the terms' form are "
            "off",
            result.sentence_after,
        ]
    else:
        answer = [
            f"missing effect partly found: {names} {closes} {share_removed(result)}",
            result.sentence_after,
            "no library term fits exactly, these are the best approximation",
            outside_the_library(result, physics),
        ]
    parts = [*answer, *preferences(result, physics), *flags(result, physics), *([] if blind else low_power(result))]
    if named := named_divergences(result):
        worst = max(named, key=lambda d: d["diverged"] / d["of"])
        parts.append(
            f"the named model's solve diverged in {len(named)} step(s), at worst on {worst['diverged']} of {worst['of']} "
            f"simulated trajectories ({worst['what']}): some inputs blow up with these coefficients"
        )
    return parts + undertrained_note(result, "the terms come from the library search")


def closest_unkept(result: Discovery) -> list[str]:
    """When nothing is kept but a searched model scored below f_p alone by at least one standard error: that model, by
    how much, and that the validation part is too small to decide, so the verdict does not read as a clean negative."""
    scored = [s for s in result.search if math.isfinite(s.versus_f_p[0]) and s.versus_f_p[1] > 0]
    closest = max(scored, key=lambda s: s.versus_f_p[0] / s.versus_f_p[1], default=None)
    if closest is None or closest.versus_f_p[0] < closest.versus_f_p[1]:
        return []
    below, error = closest.versus_f_p
    terms = ", ".join(f"{c.feature} on d{c.component}/dt" for c in closest.candidates)
    n = len(closest.fitted.heldout.rows)
    return [
        f"undecided rather than absent: the closest model, f_p + {terms}, scores {below:.3g} ± {error:.2g} below f_p "
        f"alone's held-out energy ({below / error:.1f} standard errors, two needed) on the {n} validation trajectories, "
        "too few to tell whether it describes the process or fits their noise: more measurements would decide"
    ]


def unscored_search(result: Discovery) -> str | None:
    """What the verdict says when the library search ran but scored no model, rather than that no candidate beat f_p;
    None when it scored some or did not run. The joint model of the local candidates is the divergence record with the
    most terms (its fit or its score on the validation part)."""
    if result.search_reason is None or result.search:
        return None
    joint = max((d for d in result.diverged if len(d["terms"]) > 1), key=lambda d: len(d["terms"]), default=None)
    if joint is not None:
        return (
            f"the library search could not score any candidate: the joint model of its {len(joint['terms'])} local "
            f"candidates diverged ({joint['what']}; report.md, Solves that diverged), so no term was compared with f_p alone"
        )
    return "the library search scored no candidate model, so no term was compared with f_p alone"


def undertrained_note(result: Discovery, so: str) -> list[str]:
    """The verdict's part on a grey-box whose correction was not used (``so``: what followed), when it was not."""
    if not result.undertrained:
        return []
    n = result.undertrained["validation_trajectories"]
    return [
        f"the OT grey-box does not beat f_p alone on the {n} validation trajectories by two standard errors "
        f"(undertrained, or too few to tell; the gap table is on the test part), {so}"
    ]


def share_removed(result: Discovery) -> str:
    """How much of f_p's energy distance to the test measurements the augmented physics removes, in words, from the
    test of which is nearer (:mod:`otgb.discovery.closer`; said only where it found the augmented physics nearer), with
    that test. The unbiased energy distance scatters around 0 when two samples agree, so a share over 100 % is noise,
    said so."""
    test, where = result.closer, f"to the {tested(result)} test trajectories"
    share = 1 - test.augmented / test.f_p if test.f_p > 0 else 0.0
    nearer = f"nearer than f_p alone: {test.clause()}"
    if share < 1:
        return f"{share:.0%} of f_p's energy distance {where} ({nearer})"
    left = test.augmented
    return (
        f"all of f_p's energy distance {where} (what is left, {left:.3g}, is not above zero: the test sample's noise; {nearer})"
    )


def tested(result: Discovery) -> int:
    """How many test trajectories the test of which model is nearer used (all, up to ``discover.locate_rows``)."""
    return result.closer.measured if result.closer else len(result.draws["f_p"])


def confirmed(result: Discovery) -> bool:
    """Whether the test part confirms the named terms: the augmented physics is nearer to it than f_p alone and no test
    tells it from the measurements."""
    return bool(result.found and closer_on_test(result) and closed_on_test(result))


def closer_clause(result: Discovery) -> str:
    """The test of which model is nearer, in words; where it could not run, why."""
    if result.closer is None:
        return "no test of which is nearer could run: too few of the models' trajectories stayed finite"
    return result.closer.clause()


def closer_on_test(result: Discovery) -> bool:
    """Whether the augmented physics is nearer to the test measurements than f_p alone, beyond chance
    (:mod:`otgb.discovery.closer`)."""
    return result.closer is not None and result.closer.significant


def closed_on_test(result: Discovery) -> bool:
    """Whether no test on the test part tells the augmented physics from the measurements: neither the distribution
    tests (:func:`distributions_agree`) nor, where the file recorded the inputs, the paired check."""
    return distributions_agree(result) and not inexact(result)


def distributions_agree(result: Discovery) -> bool:
    """Whether the test part's distribution tests see no difference between the augmented physics and the
    measurements: neither the disagreement map nor the gap table's C2ST (:func:`c2st_tells_apart`)."""
    after_agrees = result.after is not None and not result.after.any_significant
    return after_agrees and c2st_tells_apart(result.gap, "augmented") is None


def inexact(result: Discovery) -> bool:
    """Whether the named terms, solved on the test part's recorded inputs, miss those measurements beyond their noise."""
    return result.paired_after is not None and result.paired_after.significant


def test_part_blind(result: Discovery) -> str | None:
    """When the test part cannot tell f_p itself from the measurements, neither by the disagreement map that verifies
    the augmented physics nor by f_p's C2ST (at most 0.5 plus two of the Reference's standard deviations:
    :func:`c2st_tells_apart`), the numbers that say so; else None: why an augmented physics that agrees with such a
    part is not confirmed (the agreement would also have passed f_p), where it is not measurably nearer to it than
    f_p (:func:`closer_on_test`)."""
    f_p, reference = result.gap.get("f_p", {}), result.gap.get("reference", {})
    if "c2st" not in f_p or "c2st_std" not in reference or not math.isfinite(f_p["c2st"]):
        return None
    if getattr(result.before_on_test, "any_significant", False) or c2st_tells_apart(result.gap, "f_p"):
        return None  # the verification's own test, or the C2ST, tells f_p from this part
    return f"C2ST {f_p['c2st']:.2f}, the Reference's {reference['c2st']:.2f} +- {reference['c2st_std']:.2f}"


LOW_POWER_SPREAD = 0.1  # the Reference C2ST's spread over its repeats above which the verification is said to be weak


def low_power(result: Discovery) -> list[str]:
    """A sentence when the test part is too small for the verification to see a moderate difference: the Reference
    C2ST (half the test measurements against the other half) then spreads widely around 0.5."""
    spread = result.gap.get("reference", {}).get("c2st_std", 0.0)
    if spread <= LOW_POWER_SPREAD:
        return []
    return [
        f"with {len(result.draws['f_p'])} test trajectories the Reference C2ST spreads +- {spread:.2f} around 0.5, so the "
        "verification cannot see a difference smaller than that: more measurements would sharpen it"
    ]


def closest_alternatives(result: Discovery) -> list:
    """Per named term, the alternative closest to it on the validation measurements (evidence records)."""
    closest = []
    for candidate in result.fitted.candidates:
        mine = [c for c in result.evidence if c.replaced == candidate and math.isfinite(c.difference)]
        if mine:
            closest.append(min(mine, key=lambda c: abs(c.standard_errors)))
    return closest


def _or_alike(alternatives: list | None, physics: PhysicsModel) -> str:
    """For a named term that the measurements cannot tell from ``alternatives`` (those that fit better first): each of
    them, at the term's name, so that the verdict's first words give them all."""
    if not alternatives:
        return ""
    others = "".join(f" or {term_name(a.by, a.coefficient, physics)} ({a.by.feature})" for a in alternatives)
    errors = ", ".join(f"{a.standard_errors:+.1f}" for a in alternatives)
    better = any(a.standard_errors < 0 for a in alternatives)
    sign = "; below 0, the alternative fits the validation measurements better, by less than that noise" if better else ""
    return f"{others} (the measurements cannot tell them apart: {errors} standard errors{sign})"


def preferences(result: Discovery, physics: PhysicsModel) -> list[str]:
    """Per named term that its closest alternative does not match, how strongly the validation measurements prefer it
    (the ambiguous ones are said beside the term's name, :func:`verdict`)."""
    return [
        f"{c.replaced.feature} preferred over {term_name(c.by, c.coefficient, physics)} ({c.by.feature}) by "
        f"{c.standard_errors:.1f} standard errors"
        for c in closest_alternatives(result)
        if not c.ambiguous
    ]


def named_divergences(result: Discovery) -> list[dict]:
    """The divergence records (:mod:`otgb.discovery.log`) of the named model itself: f_p plus exactly its terms, with
    the named coefficients (not a fit's trial values, a resample's refit or a wider spread tried around them)."""
    if not result.found or result.fitted is None:
        return []
    named = set(zip(term_names(result.fitted.candidates), map(repr, result.fitted.priors)))
    return [d for d in result.diverged if set(zip(d["terms"], d.get("coefficients") or [])) == named]


def flags(result: Discovery, physics: PhysicsModel) -> list[str]:
    """The named terms whose sign contradicts their physical name, and those the measurements cannot tell from none:
    the 95 % interval of the coefficient holds zero (and, where it varies, that of its spread too)."""
    found = [(c, centre(p)) for c, p in _terms(result)]
    implausible_signs = [
        f"flagged: {term_name(c, value, physics)} ({value:+.3g} {c.feature}) {why}"
        for c, value in found
        if (why := implausible(c.feature, c.component, value, physics))
    ]
    return implausible_signs + [
        f"flagged: {term_name(c, value, physics)} ({value:+.3g} {c.feature}): its 95 % interval [{low:.3g}, {high:.3g}] "
        "holds zero, so the measurements cannot tell it from no such term"
        for (c, value), (low, high) in zip(found, _holding_zero(result))
        if low <= 0 <= high
    ]


def _holding_zero(result: Discovery) -> list[tuple[float, float]]:
    """Per named term, its coefficient's interval where neither it nor its spread's excludes zero; else (nan, nan)."""
    intervals, never = result.intervals, (math.nan, math.nan)
    if intervals is None:
        return [never] * len(_terms(result))
    spreads = intervals.width or [(0.0, 0.0)] * len(intervals.centre)
    return [centre if spread[0] <= 0 else never for centre, spread in zip(intervals.centre, spreads)]


def _terms(result: Discovery) -> list[tuple]:
    return list(zip(result.fitted.candidates, result.fitted.priors)) if result.found else []


def report_dict(result: Discovery, physics: PhysicsModel, facts: dict[str, Any]) -> dict[str, Any]:
    """``report.json``: found, verdict, terms, ambiguous, explained_r2, gap, and the details."""
    regression = {(t.candidate.feature, t.candidate.component): t for t in result.final_terms}
    terms = []
    intervals = result.intervals
    excluded = result.family.excluded_spread if result.family else None
    parts = verdict(result, physics)
    for i, (candidate, prior) in enumerate(_terms(result)):
        middle = centre(prior)
        found = regression.get((candidate.feature, candidate.component))
        terms.append(
            {
                "name": term_name(candidate, middle, physics),
                "feature": candidate.feature,
                "component": candidate.component,
                "coefficient": middle,
                "interval": list(intervals.centre[i]) if intervals else None,
                "spread_interval": list(intervals.width[i]) if intervals and intervals.width else None,
                "inclusion_probability": found.inclusion_probability if found else None,
                "r2_share": found.r2_share if found else None,
                "regression_coefficient": found.coefficient if found else None,
                "regression_interval": list(found.interval) if found else None,
                "per_trajectory": found.per_trajectory if found else None,
                "distribution": distribution(prior),
                "excluded_spread": excluded[i] if excluded else None,
                "flag": implausible(candidate.feature, candidate.component, middle, physics),
            }
        )
    return {
        "outcome": outcome(result),
        "found": result.found,
        "confirmed": confirmed(result),
        "verdict": "; ".join(parts),
        "verdict_parts": parts,
        "terms": terms,
        "ambiguous": _ambiguous(result, physics),
        "evidence": [_comparison_dict(c, physics) for c in result.evidence],
        "added_by_evidence": result.added,
        "explained_r2": {s.component: s.explained_r2 for s in result.selections},
        "gap": result.gap,
        "closer": result.closer.to_dict() if result.closer else None,
        "locate": {
            "before": result.before.to_dict(),
            "sentence_before": result.sentence_before,
            "after": result.after.to_dict() if result.after else None,
            "sentence_after": result.sentence_after,
            "paired_after": result.paired_after.to_dict() if result.paired_after else None,
        },  # fmt: skip
        "regression": [_selection_dict(s) for s in result.selections],
        "cross_check": result.cross_check,
        "route": result.route if result.found else None,
        "search_reason": result.search_reason,
        "search": [
            {
                "terms": [{"feature": c.feature, "component": c.component} for c in step.candidates],
                "g_residual": step.g_residual,
                "heldout_energy": step.fitted.heldout_energy,
                "below_f_p": step.versus_f_p[0],
                "standard_error": step.versus_f_p[1],
                "validation_trajectories": len(step.fitted.heldout.rows),
                "alternatives": [[{"feature": c.feature, "component": c.component} for c in a] for a in step.alternatives],
            }
            for step in result.search
        ],
        "search_unsupported": [
            {
                "feature": u.candidate.feature,
                "component": u.candidate.component,
                "coefficient": u.coefficient,
                "interval": list(u.interval),
            }
            for u in result.unsupported
        ],
        "family": result.fitted.family if result.fitted else None,
        "family_training_discrepancy": result.family.scores if result.family else {},
        "family_difference": {f: {"difference": d, "standard_error": e} for f, (d, e) in result.family.differences.items()}
        if result.family
        else {},
        "family_stopped_short": result.family.stopped_short if result.family else [],
        "dropped_by_heldout_check": result.dropped,
        "interval_method": intervals.method if intervals else None,
        "diverged": [d | {"named": d in named_divergences(result)} for d in result.diverged],
        "undertrained": result.undertrained,
        "correction_share": result.correction_share,
        "pointwise": result.pointwise,
        "run": facts,
    }


def _comparison_dict(comparison: Any, physics: PhysicsModel) -> dict[str, Any]:
    return {
        "feature": comparison.replaced.feature,
        "component": comparison.replaced.component,
        "alternative": comparison.by.feature,
        "alternative_name": term_name(comparison.by, comparison.coefficient, physics),
        "alternative_coefficient": comparison.coefficient,
        "difference": comparison.difference,
        "standard_error": comparison.standard_error,
        "standard_errors": comparison.standard_errors,
        "ambiguous": comparison.ambiguous,
    }


def _ambiguous(result: Discovery, physics: PhysicsModel) -> list[dict[str, Any]]:
    """Per kept term, the alternatives that the validation measurements cannot tell from it, with their numbers."""
    entries = []
    for candidate in result.fitted.candidates if result.found else []:
        mine = sorted((c for c in result.evidence if c.replaced == candidate and c.ambiguous), key=lambda c: c.standard_errors)
        close = [_comparison_dict(c, physics) for c in mine]
        if close:
            entries.append({"feature": candidate.feature, "component": candidate.component, "alternatives": close})
    return entries


def _selection_dict(selection: Any) -> dict[str, Any]:
    return {
        "component": selection.component,
        "selected": [t.candidate.feature for t in selection.terms],
        "explained_r2": selection.explained_r2,
        "condition_number": selection.condition_number,
        "confusable_pairs": [{"a": a, "b": b, "correlation": c} for a, b, c in selection.confusable_pairs],
        "inclusion_probability": selection.inclusion,
        "target_rms": selection.target_rms,
    }


def draw_locate(result: Discovery, path: Path, time_label: str) -> None:
    figure = disagreement_figure(disagreement_panels(result), time_label)
    save(figure, path)
    close(figure)


def disagreement_panels(result: Discovery) -> list[tuple[DisagreementMap, str]]:
    """The disagreement maps and their titles: f_p on the training part (where discovery looked) and, once terms
    are named, f_p (before) and the augmented physics (after) on the test part, which no fit saw: the same
    trajectories, so the last two panels compare like with like."""
    maps = [(result.before, f"f_p vs measured: the training part, {result.before.measured_trajectories}")]
    if result.before_on_test:
        test = f"the test part, {result.before_on_test.measured_trajectories}"
        maps.append((result.before_on_test, f"before: f_p vs measured, {test}"))
    if result.after:
        maps.append((result.after, f"after: augmented vs measured, the test part, {result.after.measured_trajectories}"))
    return maps


def write_report(
    run_dir: Path, result: Discovery, physics: PhysicsModel, facts: dict[str, Any], samples: dict, components: dict | None = None
) -> dict:
    """Write report.json, report.md and the figures into ``run_dir``; returns the report dict.

    ``components``: the grey-box's component analysis (:func:`otgb.analysis.components.component_analysis`),
    written as ``components.json`` and ``figures/components.png`` and summarised in the report.
    """
    figures = run_dir / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    report = report_dict(result, physics, facts)
    report["components"] = None if components is None else to_json(components)["summary"]
    if components is not None:
        (run_dir / "components.json").write_text(json.dumps(to_json(components), indent=2))
        figure = components_figure(components)
        save(figure, figures / "components.png")
        close(figure)
    (run_dir / "report.json").write_text(json.dumps(report, indent=2))
    draw_locate(result, figures / "disagreement.png", physics.axis_label("t"))
    names = [physics.axis_label(name) for name in physics.observed]
    figure = distribution_figure(samples, physics.observation_times(), names, time_label=physics.axis_label("t"))
    save(figure, figures / "distributions.png")
    close(figure)
    (run_dir / "report.md").write_text(markdown(report, facts))
    return report


def grey_box_elsewhere(facts: dict[str, Any]) -> list[str]:
    """report.md's note, where the grey-box's checkpoint was trained on other measurements than these."""
    trained_on = facts.get("grey_box_trained_on")
    return (
        [f"**Note: the grey-box's checkpoint was trained on {trained_on}, not on these measurements.**", ""] if trained_on else []
    )


def markdown(report: dict[str, Any], facts: dict[str, Any]) -> str:
    lines = [
        "# Missing-effect discovery",
        "",
        f"**Verdict:** {report['verdict_parts'][0]}",
        "",
        *(f"- {part}" for part in report["verdict_parts"][1:]),
        *([""] if len(report["verdict_parts"]) > 1 else []),
        f"Measurements: {facts.get('description', '')}",
        "",
        *grey_box_elsewhere(facts),
        "## Where f_p and the measurements disagree",
        "",
        f"{report['locate']['sentence_before']}.",
        "",
        "![disagreement map](figures/disagreement.png)",
        "",
        "Each cell (time step, component, region) compares the two samples by the energy distance; "
        "p-values from label permutations, significant cells kept by Benjamini-Hochberg at the stated false discovery rate.",
        "",
    ]
    if report["components"] is not None:
        c = report["components"]
        lines += [
            "## The grey-box's components over time",
            "",
            "Along the OT grey-box's solves (validation inputs), the learned correction f_phi makes up "
            f"{c['correction_share']:.3g} "
            "of |f_p| + |f_phi| (the paper's component analysis, Figure 3). Trajectory level: the grey-box against the "
            "held-out measurements per time step; function level needs a known vector field, which measurements alone "
            "do not give.",
            "",
            "![components](figures/components.png)",
            "",
        ]
    if report["regression"]:
        lines += _naming_section(report)
    lines += [
        "## Gap on held-out test measurements",
        "",
        "| model | MMD (paper-code) | C2ST | energy distance (raw observations) |",
        "|---|---|---|---|",
    ]
    for key, label in GAP_ROWS.items():
        if key in report["gap"]:
            g = report["gap"][key]
            lines.append(f"| {label} | {g['mmd']:.4g} | {g['c2st']:.3f} ± {g['c2st_std']:.3f} | {g['energy']:.4g} |")
    lines += _closer_line(report)
    lines += _pointwise_section(report["pointwise"])
    lines += [
        "",
        "Reference: one half of the test measurements against the other, the noise floor of these metrics (half-size samples: "
        "the biased paper-code MMD sits about twice as high as a full-size comparison at the floor; C2ST and the unbiased "
        "energy distance keep their level). All on the raw observations, each model drawn afresh from the priors: "
        "`otgb test` scores the same test part on rows standardised per time step, so its metrics.md gives other "
        "numbers, and another share of the gap closed.",
        "",
        "![distributions](figures/distributions.png)",
        "",
    ]
    return "\n".join(lines) + "\n"


def _cross_check_row(row: dict[str, Any]) -> str:
    """One strong candidate alone added to f_p: its coefficient, its lead over f_p alone, and the share of the gap it
    closes where that lead exceeds two standard errors."""
    below, error = row["below_f_p"], row["standard_error"]
    lead, closed = f"{below:.3g} ± {error:.2g}", f"{row['gap_closed']:.2f}" if below > 2 * error else "within noise"
    if not math.isfinite(row["gap_closed"]):
        lead = closed = "diverges"
    return f"| {code(row['feature'])} | d{row['component']}/dt | {row['coefficient']:.4g} | {lead} | {closed} |"


def _closer_line(report: dict[str, Any]) -> list[str]:
    """Under the gap table: whether the augmented physics is nearer to the test part than f_p (``report.json``'s
    ``closer``), or that no such test could run."""
    closer = report.get("closer")
    if closer is None:
        return ["", "No test of which model is nearer could run: too few trajectories stayed finite."] if report["found"] else []
    said = "is nearer than f_p alone" if closer["significant"] else "is not significantly nearer than f_p alone"
    diverged = f"; {closer['diverged']} of its trajectories diverged, which counts against it" if closer["diverged"] else ""
    return [
        "",
        f"The augmented physics {said}: energy distance to {closer['measured']} test measurements "
        f"{closer['augmented']:.4g} against f_p's {closer['f_p']:.4g} (from {closer['augmented_draws']} and "
        f"{closer['f_p_draws']} fresh draws, features standardised over the three samples together, so not the table's "
        f"energy column; half the measurements against the other half: {closer['floor']:.4g}); one-sided p = "
        f"{closer['pvalue']:.3g}, the larger "
        f"of a permutation test ({closer['permutation_pvalue']:.3g}, {closer['n_permutations']} relabellings of the two "
        f"models' trajectories) and a normal test that counts the measurements' own sampling noise "
        f"({closer['normal_pvalue']:.3g}); threshold {closer['alpha']:g}{diverged}. This test decides whether the named "
        "terms are confirmed.",
    ]


def _naming_section(report: dict[str, Any]) -> list[str]:
    lines = ["## What the learned correction is", ""]
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
    if report["terms"]:
        lines += [
            "",
            "| term | feature | on | coefficient | 95 % interval | inclusion | f_phi's slope [95 %] "
            "| share of f_phi (R^2) | distribution |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for t in report["terms"]:
            interval = f"[{t['interval'][0]:.4g}, {t['interval'][1]:.4g}]" if t["interval"] else "-"
            inclusion = f"{t['inclusion_probability']:.2f}" if t["inclusion_probability"] is not None else "-"
            share = f"{t['r2_share']:.3f}" if t["r2_share"] is not None else "-"
            slope = (
                f"{t['regression_coefficient']:.4g} [{t['regression_interval'][0]:.4g}, {t['regression_interval'][1]:.4g}]"
                if t["regression_coefficient"] is not None
                else "-"
            )
            dist = distribution_text(t["distribution"])
            lines.append(
                f"| {t['name']} | {code(t['feature'])} | d{t['component']}/dt | {t['coefficient']:.4g} | {interval} "
                f"| {inclusion} | {slope} | {share} | {dist} |"
            )
    if report["terms"] and report["interval_method"]:
        form = (
            " They hold for the named term's form; an ambiguous alternative (below) has its own coefficient."
            if report["ambiguous"]
            else ""
        )
        lines.append(f"\n95 % intervals: {report['interval_method']} (docs/discovery.md gives their measured coverage).{form}")
    elif report["terms"]:
        lines.append("\nNo intervals: the fit's discrepancy is not at a minimum there (its Hessian is not positive definite).")
    for t in report["terms"]:
        if t["flag"]:
            lines.append(f"\n**Flagged:** {t['name']} ({t['coefficient']:+.4g} {code(t['feature'])}) {t['flag']}.")
    if report["undertrained"]:
        u = report["undertrained"]
        said = undertrained_text(
            u["difference"], u["standard_error"], u["validation_trajectories"], u["greybox_heldout_energy"],
            u["f_p_heldout_energy"],
        )  # fmt: skip
        lines.append(f"\n**The OT grey-box's correction is not used:** it {said}.")
    if report["diverged"]:
        lines += ["", "### Solves that diverged", ""]
        lines.append(
            "A fit or a score whose solve diverged counts its model as infinitely worse in that step; a verification leaves "
            "the diverged trajectories out. **named**: the model this report names."
        )
        lines += ["", "| step | f_p plus | diverged trajectories | first inputs |", "|---|---|---|---|"]
        for d in report["diverged"]:
            terms = ", ".join(code(t) for t in d["terms"]) or "nothing"
            terms += " (**named**)" if d.get("named") else ""
            if d.get("coefficients"):
                terms += f" with {', '.join(d['coefficients'])}"
            first = ", ".join(f"{v:.4g}" for v in d["first_inputs"]) if d["first_inputs"] else "-"
            lines.append(f"| {d['what']} | {terms} | {d['diverged']} of {d['of']} | {first} |")
    lines += _evidence_section(report)
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
    lines += [_cross_check_row(row) for row in report["cross_check"]]
    lines += _search_section(report)
    if report["dropped_by_heldout_check"]:
        lines.append("")
        dropped = ", ".join(f"`{d['feature']}`" for d in report["dropped_by_heldout_check"])
        lines.append(f"Dropped (no held-out gain beside the kept terms; swapped for a named term: the evidence above): {dropped}")
    lines += _family_section(report)
    if report["locate"]["sentence_after"]:
        lines += ["", f"After the fix: {report['locate']['sentence_after']}."]
    return lines + [""]


def _evidence_section(report: dict[str, Any]) -> list[str]:
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


def _family_section(report: dict[str, Any]) -> list[str]:
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
        if k not in ("constant", report["family"]) and d["difference"] <= 2 * d["standard_error"]
    ]
    noise = report.get("run", {}).get("measurement_noise") or 0.0
    if noise > 0:
        lines.append(f"Every simulation compared with the measurements carried white noise of sd {noise:.4g} (theirs).")
    elif report["family"] != "constant":
        lines.append(
            "The simulations carried no measurement noise (data.measurement_noise 0): noise in the measurements "
            "widens their spread at every time, as a coefficient that varies between trajectories would. Where the "
            "measurements are noisy, read this family as a varying coefficient or measurement noise, or give their "
            "noise's sd as data.measurement_noise (docs/discovery.md, measurement noise)."
        )
    if report["family"] != "constant" and alike:
        lines.append(
            f"The training measurements cannot tell the {report['family']} family from {' or '.join(alike)} (within two "
            "standard errors): that the coefficient varies is shown, the shape of its distribution is not."
        )
    for family in report["family_stopped_short"]:
        lines.append(
            f"The {family} fit scored no better than the constant, which its family contains (zero width): "
            "it was taken at zero width."
        )
    for t in report["terms"]:
        if t["spread_interval"]:
            low, high = t["spread_interval"]
            spread = f"95 % interval [{low:.4g}, {high:.4g}]"
            lines.append(f"Spread of {code(t['feature'])} (half-width or standard deviation): {spread}.")
        elif report["family"] == "constant":
            lines.append(f"{code(t['feature'])} is constant; " + _spread_bound(t["excluded_spread"]))
    return lines


def _spread_bound(bound: float | None) -> str:
    if bound is None:
        return f"the data cannot exclude a spread up to {FIRST_SPREAD * 2**SPREAD_DOUBLINGS:.3g} times its size."
    return (
        f"a spread wider than {bound:.3g} (half-width; standard deviation if only the normal family is tried) "
        "is excluded by the data (two standard errors)."
    )


def _search_section(report: dict) -> list[str]:
    """The library search's path (when f_phi's route left the gap open), and which route named the terms."""
    if not report["search"]:
        return []
    lines = ["", "### Library search: every local candidate fitted together, then the best subset of each size", ""]
    if report.get("search_reason"):
        lines += [f"It ran because {report['search_reason']}.", ""]
    first = report["search"][0]
    lines += [
        f"Held-out energy: on the {first['validation_trajectories']} validation trajectories, lower is better; a model is "
        "kept only where it is below f_p alone's by more than two standard errors of the difference.",
        "",
        "| terms | residual of g (relative RMS) | held-out energy | below f_p alone's (± standard error) |",
        "|---|---|---|---|",
        f"| f_p alone | - | {first['heldout_energy'] + first['below_f_p']:.4g} | - |",
    ]
    for step in report["search"]:
        terms = ", ".join(f"{code(t['feature'])} on d{t['component']}/dt" for t in step["terms"])
        below = f"{step['below_f_p']:.3g} ± {step['standard_error']:.2g}"
        lines.append(f"| {terms} | {step['g_residual']:.3f} | {step['heldout_energy']:.4g} | {below} |")
    if unsupported := report.get("search_unsupported"):
        dropped = "; ".join(
            f"{code(u['feature'])} on d{u['component']}/dt (coefficient {u['coefficient']:.3g}, interval "
            f"[{u['interval'][0]:.3g}, {u['interval'][1]:.3g}])"
            for u in unsupported
        )
        lines += ["", f"Dropped from the search's model, their coefficients' 95 % intervals holding zero: {dropped}."]
    return lines + ["", f"Terms named by: **{report['route']}**." if report["route"] else "Nothing kept."]


def _pointwise_section(pointwise: dict) -> list[str]:
    """ABS ERR / N-RMSE against a known DGP, over the training horizon and the next one (extrapolation)."""
    if not pointwise:
        return []
    lines = ["", "Against the known DGP, on the test inputs (the second horizon is extrapolation):", ""]
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


def augmented_config(config: dict[str, Any], physics: PhysicsModel, result: Discovery) -> dict[str, Any]:
    """The run's config with ``data.physics`` replaced by f_p plus the named terms (earlier rounds' kept)."""
    config = {k: v for k, v in config.items() if k not in ("discover", "ckpt_path", "config")}
    physics_entry = config["data"]["physics"]
    earlier = []
    if isinstance(physics, Augmented):
        physics_entry, earlier = physics_entry["init_args"]["base"], physics_entry["init_args"]["terms"]
    new = [
        {"class_path": "otgb.physics.LibraryTerm",
         "init_args": {"feature": c.feature, "component": c.component, "coefficient": prior_dict(p)}}
        for c, p in _terms(result)
    ]  # fmt: skip
    config["data"]["physics"] = {
        "class_path": "otgb.physics.Augmented",
        "init_args": {"base": physics_entry, "terms": earlier + new},
    }
    for logger in config["trainer"].get("logger") or []:  # the next round's logs: runs/augmented/<a new version_N>
        if isinstance(logger, dict) and "name" in logger.get("init_args", {}):
            logger["init_args"].update(name="auto", version=None)
    return config


def write_augmented(path: Path, config: dict[str, Any]) -> None:
    header = "# Written by otgb discover: the run's config with f_p augmented by the named terms.\n"
    path.write_text(header + yaml.safe_dump(config, sort_keys=False))
