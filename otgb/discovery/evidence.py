"""Evidence from the measurements for every named term: the kept model against its close alternatives.

For each term of the kept model, each close alternative is swapped in for it alone: the strong
candidates on the same component that closed part of the gap when added to f_p alone
(:func:`otgb.discovery.naming.cross_check_step`), the library terms it moves with along the
grey-box's solves (the regression's confusable pairs, :data:`otgb.discovery.regression.CONFUSABLE`:
a term that never became a strong candidate may still fit the measurements alike, u^3 for u^2)
and, where the term is a friction of a velocity (``v``, ``v*|v|``, ``v^3``), Coulomb friction
``sign(v)``. The swapped model's coefficients are fitted by distribution matching on the training
measurements and scored on the validation measurements with the same simulation draws as the kept
model (common random numbers), so the difference of their held-out discrepancies and its standard
error (:func:`otgb.discovery.scores.difference`) come from data that no fit saw.

An alternative within two standard errors is *ambiguous*: the measurements cannot tell it from
the named term. Of those that fit better by more than two standard errors, the one that lowers the
held-out discrepancy most replaces the named term (and the comparisons are made again around the
new model), so every kept term is the one the measurements prefer among its alternatives, by the
number of standard errors the report gives. Where the measurements cannot choose, physics does: a
kept term whose sign contradicts its name (anti-drag, negative damping, anti-diffusion) is replaced
by an ambiguous alternative of the same kind whose sign is right (a saturating friction fitted as
friction plus anti-drag becomes friction plus Coulomb friction, when the data cannot tell the two
apart; a spring is no replacement for a friction).

Then each strong candidate not yet kept is *added* to the kept model (its coefficient started at
zero, so the richer fit starts where the kept model is): forward selection follows f_phi's ranking,
and a network that learned friction and drag together as one mostly linear friction ranks drag
low. An addition is taken when it fits the validation measurements better by more than two
standard errors *and* the 95 % interval of its own coefficient (fitted on the training
measurements) excludes zero: several additions are tried and the best is kept, so a term that only
helps by chance can clear two standard errors, but its coefficient then sits at zero. Among the
additions within two standard errors of the best one, the measurements cannot choose, and the one
that closed most of f_p's gap alone (the cross-check's order) is taken. The swaps are then weighed
again around the larger model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from otgb.discovery.library import Candidate, implausible, signed_kind
from otgb.discovery.log import progress
from otgb.discovery.refine import FittedTerms
from otgb.discovery.regression import Selection
from otgb.discovery.scores import STANDARD_ERRORS, beats, difference
from otgb.physics.base import PhysicsModel

MAX_SWAPS = 3  # rounds in which a better alternative replaces a kept term
MAX_ADDITIONS = 2  # strong candidates added to the kept model


@dataclass
class Comparison:
    """The kept model against the same model with ``replaced`` swapped for ``by``, on the validation measurements."""

    replaced: Candidate
    by: Candidate
    coefficient: float  # ``by``'s fitted coefficient
    difference: float  # the alternative's held-out discrepancy minus the kept model's: > 0 where the kept one fits better
    standard_error: float

    @property
    def standard_errors(self) -> float:
        """How many standard errors the measurements prefer the kept term by (negative: the alternative)."""
        if not math.isfinite(self.difference):
            return self.difference
        if self.standard_error > 0:
            return self.difference / self.standard_error
        return 0.0 if self.difference == 0 else math.copysign(math.inf, self.difference)

    @property
    def ambiguous(self) -> bool:
        """Whether the measurements cannot tell the two apart (within two standard errors)."""
        return math.isfinite(self.difference) and abs(self.standard_errors) <= STANDARD_ERRORS


Refit = Callable[[list[Candidate], list[float]], FittedTerms]  # constant coefficients fitted from a start
Interval = Callable[[FittedTerms], "tuple[float, float] | None"]  # the last coefficient's 95 % interval, None if none
Partners = Mapping[Candidate, Sequence[Candidate]]  # per library term, the terms it moves with (:func:`moves_with`)


def moves_with(selections: Sequence[Selection]) -> dict[Candidate, list[Candidate]]:
    """Per library term, the terms on its component that it moves with along the grey-box's solves: the regression's
    confusable pairs (|correlation| >= :data:`otgb.discovery.regression.CONFUSABLE`), most correlated first."""
    pairs = sorted(
        ((Candidate(a, s.component), Candidate(b, s.component), abs(r)) for s in selections for a, b, r in s.confusable_pairs),
        key=lambda pair: -pair[2],
    )
    partners: dict[Candidate, list[Candidate]] = {}
    for first, second, _ in pairs:
        partners.setdefault(first, []).append(second)
        partners.setdefault(second, []).append(first)
    return partners


def alternatives(
    physics: PhysicsModel, kept: list[Candidate], cross_check: list[dict], per_term: int, partners: Partners
) -> list[tuple]:  # fmt: skip
    """(index of a kept term, its alternative, its start): per kept term, the ``per_term`` cross-checked candidates on
    its component that closed most of the gap alone, the terms it moves with (``partners``), and Coulomb friction for a
    velocity's friction; never a term the kept model holds. The start is the coefficient the cross-check fitted to the
    alternative alone (for one of those ``per_term`` candidates, or a partner whose fit stayed finite), else None."""
    swaps = []
    for index, term in enumerate(kept):
        rows = {Candidate(r["feature"], r["component"]): r for r in cross_check if r["component"] == term.component}
        closing = [c for c, r in rows.items() if c not in kept and math.isfinite(r["gap_closed"]) and r["gap_closed"] > 0]
        closing, partnered = closing[:per_term], list(partners.get(term, ()))
        fitted_alone = closing + [c for c in partnered if c in rows and math.isfinite(rows[c]["gap_closed"])]
        coulomb = [Candidate(f"sign({term.component})", term.component)] if _is_friction(term, physics) else []
        options = closing + partnered + coulomb
        for candidate in dict.fromkeys(c for c in options if c not in kept):
            start = rows[candidate]["coefficient"] if candidate in fitted_alone else math.nan
            swaps.append((index, candidate, start if math.isfinite(start) else None))
    return swaps


def _is_friction(term: Candidate, physics: PhysicsModel) -> bool:
    v = term.component
    return v in physics.velocity_names and term.feature in (v, f"{v}*|{v}|", f"{v}^3")


def weigh(
    physics: PhysicsModel, kept: FittedTerms, cross_check: list[dict], per_term: int, refit: Refit, start: Callable,
    interval: Interval, partners: Partners | None = None,
):  # fmt: skip
    """The kept model (a better alternative swapped in, up to ``MAX_SWAPS`` times; a strong candidate added, up to
    ``MAX_ADDITIONS`` times), its :class:`Comparison` s, and the additions (feature, component, difference, its
    standard error: the kept model's held-out discrepancy minus the larger model's; the added coefficient's interval).

    ``refit(candidates, init)`` fits constant coefficients and scores them on the validation part;
    ``start(candidate)`` gives a coefficient's starting value where the cross-check has none;
    ``interval(fitted)`` gives the 95 % interval of the last coefficient of a fit;
    ``partners`` gives the terms each library term moves with (:func:`moves_with`; none if not given).
    """

    def offered(candidates: list[Candidate]) -> list[tuple]:
        return alternatives(physics, candidates, cross_check, per_term, partners or {})

    kept, compared = _swap(physics, kept, offered, refit, start)
    added = []
    for _ in range(MAX_ADDITIONS):
        addition = _addition(kept, cross_check, per_term, refit, interval)
        if addition is None:
            break
        larger, (low, high) = addition
        gap, error = difference(larger.heldout, kept.heldout)
        term = larger.candidates[-1]
        added.append({
            "feature": term.feature, "component": term.component, "difference": gap, "standard_error": error,
            "coefficient": larger.priors[-1].value, "interval": [low, high],
        })  # fmt: skip
        kept, compared = _swap(physics, larger, offered, refit, start)
    return kept, compared, added


def _swap(physics, kept: FittedTerms, offered: Callable, refit: Refit, start: Callable):
    """The kept model after up to ``MAX_SWAPS`` swaps (:func:`choose_swap`) among the alternatives ``offered`` for its
    terms (:func:`alternatives`), and its :class:`Comparison` s."""
    compared = _compare(kept, offered, refit, start)
    for _ in range(MAX_SWAPS):
        chosen = choose_swap(physics, kept, compared)
        if chosen is None:
            break
        comparison, kept = chosen
        by, replaced = comparison.by.feature, comparison.replaced.feature
        errors = comparison.standard_errors
        if errors < -STANDARD_ERRORS:
            progress(f"evidence: {by} fits the validation measurements better than {replaced} by {-errors:.1f} standard errors")
        else:
            progress(f"evidence: {replaced} has the wrong sign for its physics; the measurements cannot tell it from {by}")
        progress(f"evidence: {by} swapped in for {replaced} ({errors:+.1f} standard errors)")
        compared = _compare(kept, offered, refit, start)
    return kept, [c for c, _ in compared]


def choose_swap(physics: PhysicsModel, kept: FittedTerms, compared: list[tuple]) -> tuple | None:
    """Of (:class:`Comparison`, the swapped model's fit) pairs, the swap to make: an alternative that fits the
    validation measurements better by more than two standard errors (the largest improvement); else, for a kept
    term whose sign contradicts its physics (:func:`otgb.discovery.library.implausible`), an alternative of the same
    kind (a friction for a friction) with the right sign that the measurements cannot tell from it (the best fitting
    one); None if neither."""
    better = [pair for pair in compared if pair[0].standard_errors < -STANDARD_ERRORS]
    if better:
        return min(better, key=lambda pair: pair[0].difference)
    value = dict(zip(kept.candidates, (p.value for p in kept.priors)))
    plausible = [
        pair for pair in compared
        if (c := pair[0]).ambiguous and implausible(c.replaced.feature, c.replaced.component, value[c.replaced], physics)
        and signed_kind(c.by.feature, c.by.component, physics) == signed_kind(c.replaced.feature, c.replaced.component, physics)
        and not implausible(c.by.feature, c.by.component, c.coefficient, physics)
    ]  # fmt: skip
    return min(plausible, key=lambda pair: pair[0].difference, default=None)


def _compare(kept: FittedTerms, offered: Callable, refit: Refit, start: Callable) -> list[tuple]:
    """(:class:`Comparison`, the swapped model's fit) for each alternative ``offered`` for the terms of ``kept``."""
    compared = []
    for index, by, value in offered(kept.candidates):
        candidates = [by if i == index else c for i, c in enumerate(kept.candidates)]
        init = [p.value for p in kept.priors]
        init[index] = start(by) if value is None else value
        swapped = refit(candidates, init)
        gap, error = difference(kept.heldout, swapped.heldout)
        compared.append((Comparison(kept.candidates[index], by, swapped.priors[index].value, gap, error), swapped))
    return compared


def _addition(kept: FittedTerms, cross_check: list[dict], per_term: int, refit: Refit, interval: Interval):
    """The kept model with one more strong candidate and that coefficient's interval, if the candidate fits the
    validation measurements better by two standard errors and its interval excludes zero; of the additions within
    two standard errors of the best, the first in the cross-check's order. None if no candidate qualifies."""
    options = [
        Candidate(r["feature"], r["component"]) for r in cross_check
        if math.isfinite(r["gap_closed"]) and r["gap_closed"] > 0
    ]  # fmt: skip
    options = [c for c in dict.fromkeys(options) if c not in kept.candidates][: per_term * 2]
    larger = [refit([*kept.candidates, c], [*(p.value for p in kept.priors), 0.0]) for c in options]
    better = []
    for fitted in larger:
        gap, error = difference(fitted.heldout, kept.heldout)
        line = f"evidence: adding {fitted.candidates[-1].feature}: {gap / error if error > 0 else 0.0:+.1f} standard errors"
        if beats(fitted.heldout, kept.heldout):
            bounds = interval(fitted)
            if bounds is None:
                line += "; not taken: its coefficient has no interval (the fit is not at a minimum)"
            elif bounds[0] <= 0 <= bounds[1]:
                line += f"; not taken: its coefficient's 95 % interval [{bounds[0]:.3g}, {bounds[1]:.3g}] holds zero"
            else:
                better.append((fitted, bounds))
        progress(line)
    if not better:
        return None
    best = min(better, key=lambda pair: pair[0].heldout_energy)[0]
    chosen = next(pair for pair in better if not beats(best.heldout, pair[0].heldout))  # better keeps the cross-check's order
    progress(f"evidence: {chosen[0].candidates[-1].feature} added: it fits the validation measurements better")
    return chosen
