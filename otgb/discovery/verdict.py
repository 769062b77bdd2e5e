"""The verdict of a discovery, computed from its result in one place: the outcome, whether the test part confirms
it, and every sentence the report and the terminal show (the writers only render them)."""

from __future__ import annotations

import math

from otgb.discovery.crossfit import heldout_part
from otgb.discovery.families import centre
from otgb.discovery.library import fixed_in_space, implausible, term_name
from otgb.discovery.record import Discovery
from otgb.discovery.scores import term_names
from otgb.discovery.verify import c2st_tells_apart
from otgb.physics.base import PhysicsModel

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
    if not result.before.any_significant and not result.recalibrated:
        return "nothing detected"
    if not result.explained:
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
        return ["no missing effect detected: " + result.sentence_before, *(r.unconfirmed() for r in [result.recalibration] if r)]
    if kind == "nothing found":
        return nothing_found(result, physics)
    blind = test_part_blind(result) if kind == "named, not confirmed" and closed_on_test(result) else None
    answer = answer_named(result, physics, kind, blind)
    forms = result.forms.said(physics) if result.forms and result.found else []
    parts = [*answer, *forms, *recalibration_alike(result), *preferences(result, physics), *flags(result, physics)]
    parts += [] if blind else low_power(result)
    if named := named_divergences(result):
        worst = max(named, key=lambda d: d["diverged"] / d["of"])
        parts.append(
            f"the named model's solve diverged in {len(named)} step(s), at worst on {worst['diverged']} of {worst['of']} "
            f"simulated trajectories ({worst['what']}): some inputs blow up with these coefficients"
        )
    so = "the terms come from the library search" if result.found else "f_p's priors were refitted"
    return parts + undertrained_note(result, so)


def nothing_found(result: Discovery, physics: PhysicsModel) -> list[str]:
    """The verdict where the measurements differ from f_p but no library term was kept."""
    better = f"no candidate term fits {heldout_part(result.evidence_on is not None)} better than f_p alone by two standard errors"
    why = unscored_search(result) or better
    return [
        f"no missing effect found in the library: the measurements differ from f_p ({result.sentence_before}), but {why}",
        *closest_unkept(result),
        outside_the_library(result, physics),
        *undertrained_note(result, "and the library search named nothing"),
        *low_power(result),
    ]


def named_terms_text(result: Discovery, physics: PhysicsModel) -> str:
    """The kept terms by physical name and form, each with the alternatives the measurements cannot tell it from."""
    ambiguous: dict[tuple[str, str], list] = {}
    for c in sorted(result.evidence, key=lambda c: c.standard_errors):  # those that fit better than the named term first
        if c.ambiguous and math.isfinite(c.difference):
            ambiguous.setdefault((c.replaced.feature, c.replaced.component), []).append(c)
    return ", ".join(
        f"{term_name(c, centre(p), physics)} ({c.feature} on d{c.component}/dt)"
        + _or_alike(ambiguous.get((c.feature, c.component)), physics)
        for c, p in kept_terms(result)
    )


def answer_named(result: Discovery, physics: PhysicsModel, kind: str, blind: str | None) -> list[str]:
    """The answer's parts where terms were named: the outcome ``kind`` with its numbers and the sentence after the fix
    (``blind``: why the test part cannot confirm anything, where it cannot tell even f_p from the measurements)."""
    names = named_terms_text(result, physics) if result.found else result.recalibration.answer_text()
    names += result.recalibration.beside_text() if result.found and result.recalibrated else ""
    what = "missing effect" if result.found else "miscalibration"  # terms named, or f_p's priors refitted
    removes, closes = ("removes", "closes") if len(kept_terms(result)) <= 1 else ("remove", "close")
    if blind:
        return [
            f"{what} named, not confirmed: {names}, but the {len(result.draws['f_p'])} test trajectories cannot "
            f"tell even f_p from the measurements ({blind}), nor the augmented physics as nearer to them than f_p "
            f"({closer_clause(result)}), so their agreeing with the augmented physics confirms nothing: more "
            "measurements are needed to confirm it"
        ]
    if kind == "named, not confirmed":
        test = result.closer
        versus = (
            f"energy distance {test.augmented:.3g} against f_p's {test.f_p:.3g}, from {test.augmented_draws} and "
            f"{test.f_p_draws} draws; half the test measurements against the other half: {test.floor:.3g}; "
            if test
            else ""
        )
        part = heldout_part(result.evidence_on is not None)
        return [
            f"{what} named, not confirmed: {names} fit {part} better than f_p alone, but on the "
            f"{tested(result)} test trajectories, which no fit saw, the augmented physics is not significantly nearer "
            f"to the measurements than f_p alone ({versus}{closer_clause(result)})",
            result.sentence_after,
            *([outside_the_library(result, physics)] if result.found else []),
        ]
    if kind == "gap closed":
        return [
            f"{what} found, the gap is closed as far as the test part can tell: {names} {removes} "
            f"{share_removed(result)}, and no test tells the augmented physics from them",
            result.sentence_after,
        ]
    if kind == "found, not exactly":  # the distributions agree, the recorded inputs do not
        return [
            f"{what} found, not exactly: {names} {removes} {share_removed(result)} and the distribution tests "
            "see no difference on the test part, but solved on its recorded inputs the augmented physics misses the "
            "measurements by more than their noise: the coefficients (fitted to distributions) or the terms' form are "
            "off",
            result.sentence_after,
        ]
    return [
        f"{what} partly found: {names} {closes} {share_removed(result)}",
        result.sentence_after,
        "no library term fits exactly, these are the best approximation",
        *([outside_the_library(result, physics)] if result.found else []),
    ]


def recalibration_alike(result: Discovery) -> list[str]:
    """Where terms were named and f_p with recalibrated priors also beats f_p alone, but neither beats the other on
    the validation part: that the measurements cannot tell a missing term from priors that are off."""
    alike = result.found and result.recalibration and not result.recalibrated  # not where the answer holds both
    said = result.recalibration.alike(result.fitted.heldout) if alike else None
    return [said] if said else []


def closest_unkept(result: Discovery) -> list[str]:
    """When nothing is kept but a searched model scored below f_p alone by at least one standard error: that model, by
    how much, and that the validation part is too small to decide, so the verdict does not read as a clean negative."""
    scored = [s for s in result.search if math.isfinite(s.versus_f_p[0]) and s.versus_f_p[1] > 0]
    closest = max(scored, key=lambda s: s.versus_f_p[0] / s.versus_f_p[1], default=None)
    if closest is None or closest.versus_f_p[0] < closest.versus_f_p[1]:
        return []
    below, error = closest.versus_f_p
    terms = ", ".join(f"{c.feature} on d{c.component}/dt" for c in closest.candidates)
    scored_on = result.evidence_on or f"the {len(closest.fitted.heldout.rows)} validation trajectories"
    return [
        f"undecided rather than absent: the closest model, f_p + {terms}, scores {below:.3g} ± {error:.2g} below f_p "
        f"alone's held-out energy ({below / error:.1f} standard errors, two needed) on {scored_on}, "
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
    return bool(result.explained and closer_on_test(result) and closed_on_test(result))


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
    for candidate, _ in kept_terms(result):
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
    found = [(c, centre(p)) for c, p in kept_terms(result)]
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
        return [never] * len(kept_terms(result))
    spreads = intervals.width or [(0.0, 0.0)] * len(intervals.centre)
    return [centre if spread[0] <= 0 else never for centre, spread in zip(intervals.centre, spreads)]


def kept_terms(result: Discovery) -> list[tuple]:
    return list(zip(result.fitted.candidates, result.fitted.priors)) if result.found else []


def undertrained_text(gain: float, error: float, n: int, greybox: float, alone: float) -> str:
    """Why the grey-box's correction is not used, with the numbers: no better than f_p, or better by less than two
    standard errors of the difference on these ``n`` validation trajectories (too few to tell, or undertrained)."""
    numbers = f"energy {greybox:.4g} against {alone:.4g}, difference {gain:.3g} ± {error:.2g}"
    if gain > 0:
        judged = (
            f"fits the {n} validation measurements better than f_p alone, but not by two standard errors ({numbers}): "
            "they are too few to tell, or the grey-box is undertrained; more measurements, or a larger "
            "data.simulation_budget"
        )
    else:
        judged = (
            f"fits the {n} validation measurements no better than f_p alone ({numbers}): it is undertrained; raise "
            "data.simulation_budget (or give a longer-trained --ckpt_path)"
        )
    return f"{judged}. Its correction is not used to name terms: the naming relies on the library search"
