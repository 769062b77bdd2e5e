"""Whether an effect varies between trajectories: the coefficients' prior family, and the spread the data allow.

The families are nested: a uniform U(c - w, c + w), a normal N(c, w^2) or a two-point
{c - w, c + w} of zero width is the constant c. Each richer family is fitted from the constant's optimum
(:func:`otgb.discovery.refine.fit`) and scored on the training measurements with the same
simulation draws as the constant (common random numbers, ``FAMILY_REPEATS`` draws), or, with
cross-fitted evidence (:mod:`otgb.discovery.crossfit`), by each fit's cross-fitted scores. A richer
fit that scores worse than the constant on the training measurements stopped short of the optimum
its family contains (it cannot be worse at zero width); it is then taken at zero width, where it
ties the constant, and the report says so (out of sample, worse is the spread's overfitting, and
the richer fit stands to be weighed). The simplest family that no richer family beats by two standard errors
(:func:`otgb.discovery.scores.beats`) is chosen, and every family's difference to it is
reported with its standard error. A family that varies is kept only where the 95 % interval of
every term's spread excludes zero (:mod:`otgb.discovery.intervals`) and it scores lower than the
constant on the validation part, which no fit saw; otherwise the constant is chosen and the
report says why (:attr:`FamilyChoice.rejected`).

When the constant is chosen, :func:`excluded_spread` says how wide a spread the data still
allow: per term, the smallest half-width (uniform; standard deviation for a normal) around the
constant that the constant beats by two standard errors, found by doubling and then bisection.
When a family that varies is chosen, the spread's 95 % interval comes from
:mod:`otgb.discovery.intervals`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from torch import Tensor

from otgb.discovery.families import CONSTANT, FAMILIES, SPREAD_FAMILIES, prior, varies
from otgb.discovery.intervals import Intervals
from otgb.discovery.refine import FAMILY_REPEATS, MIN_WIDTH, FittedTerms
from otgb.discovery.scores import Scores, beats, difference, discrepancies
from otgb.physics.base import PhysicsModel
from otgb.physics.priors import Constant, Prior

FIRST_SPREAD = 0.02  # the first half-width tried by excluded_spread, in units of the coefficient's size
SPREAD_DOUBLINGS = 8
SPREAD_BISECTIONS = 2
SPREAD_REPEATS = 10  # simulation draws per score of a spread (common random numbers: the measured sample dominates)


@dataclass(frozen=True)
class FamilyChoice:
    """The chosen family's fit, each family's score and difference to it, the fits that stopped short."""

    fitted: FittedTerms
    scores: dict[str, float]  # mean discrepancy per family (to the training measurements, or cross-fitted)
    differences: dict[str, tuple[float, float]]  # per family: its score minus the chosen one's, and its standard error
    stopped_short: list[str] = field(default_factory=list)  # families whose fit ended worse than the constant
    excluded_spread: list[float | None] | None = None  # constant chosen: per term, the smallest spread the data exclude
    rejected: dict[str, str] = field(default_factory=dict)  # a family the scores chose, and why it was not kept
    rejected_fit: FittedTerms | None = None  # that family's fit


def choose_family(fits: list[FittedTerms], scores: dict[str, Scores]) -> FittedTerms:
    """The simplest family (``FAMILIES`` order) that no richer family beats, by their ``scores``."""
    ordered = sorted(fits, key=lambda f: FAMILIES.index(f.family))
    chosen = ordered[0]
    for richer in ordered[1:]:
        if beats(scores[richer.family], scores[chosen.family]):
            chosen = richer
    return chosen


def choose_prior(
    physics: PhysicsModel, constant: FittedTerms, measured: Tensor, families: tuple[str, ...], refit: Callable, seed: int,
    interval: Callable[[FittedTerms], Intervals | None] | None = None, cross_fitted: bool = False,
) -> FamilyChoice:  # fmt: skip
    """Each family of ``families`` for ``constant``'s terms (``refit(family)`` fits one from the constant's optimum,
    the constant itself again too), scored on ``measured`` (with ``cross_fitted``, by each fit's own cross-fitted
    held-out scores, :mod:`otgb.discovery.crossfit`); the nested check, the choice (a family that varies kept only as
    :func:`unsupported_spread` allows, with ``interval`` the 95 % intervals of a fit), and the spread the data allow if
    the constant is chosen (on ``measured``)."""
    on_measured = lambda f: discrepancies(physics, f.candidates, f.priors, measured, seed, FAMILY_REPEATS)  # noqa: E731
    score = (lambda f: f.heldout) if cross_fitted else on_measured
    constant = refit(CONSTANT)  # on the families' samples
    fits, scores, stopped_short = [constant], {CONSTANT: score(constant)}, []
    for family in filter(varies, families):
        richer = refit(family)
        scores[family] = score(richer)
        if not cross_fitted and difference(scores[CONSTANT], scores[family])[0] > 0:  # worse than its width-zero member
            stopped_short.append(family)
            richer, scores[family] = at_zero_width(richer, constant), scores[CONSTANT]
        fits.append(richer)
    fits = [f for f in fits if f.family in families] or [constant]
    chosen, rejected, rejected_fit = choose_family(fits, scores), {}, None
    if varies(chosen.family) and interval is not None and (reason := unsupported_spread(chosen, constant, interval)):
        chosen, rejected, rejected_fit = constant, {chosen.family: reason}, chosen
    differences = {f.family: difference(scores[chosen.family], scores[f.family]) for f in fits}
    excluded = None
    if not varies(chosen.family):
        spread_family = next((f for f in SPREAD_FAMILIES if f in families), SPREAD_FAMILIES[0])
        terms = range(len(constant.candidates))
        excluded = [excluded_spread(physics, constant, k, spread_family, measured, seed) for k in terms]
    means = {f.family: scores[f.family].mean for f in fits}
    return FamilyChoice(chosen, means, differences, stopped_short, excluded, rejected, rejected_fit)


def unsupported_spread(
    richer: FittedTerms, constant: FittedTerms, interval: Callable[[FittedTerms], Intervals | None]
) -> str | None:
    """Why the spread of ``richer`` (a family that varies) is not supported, or None where it is: the 95 % interval of
    every term's spread excludes zero, and ``richer`` scores lower than ``constant`` on the validation part."""
    intervals = interval(richer)
    if intervals is None or intervals.width is None:
        return "its spread has no 95 % interval (the fit is not at a minimum of the discrepancy)"
    held = [low <= 0 for low, _ in intervals.width]
    if any(held):
        names = [c.feature for c, holds in zip(richer.candidates, held) if holds]
        return f"the 95 % interval of the spread of {', '.join(names)} holds zero"
    if richer.heldout.mean >= constant.heldout.mean:
        return "it fits the validation part no better than the constant"
    return None


def at_zero_width(richer: FittedTerms, constant: FittedTerms) -> FittedTerms:
    """``richer``'s family at the constant's centres and (nearly) zero width: the constant as a member of the family."""
    sizes = richer.scales or [abs(p.value) for p in constant.priors]
    priors = [prior(richer.family, p.value, MIN_WIDTH * max(size, 1e-12)) for p, size in zip(constant.priors, sizes)]
    candidates = list(constant.candidates)
    return FittedTerms(richer.family, candidates, priors, constant.heldout, richer.loss, richer.start, richer.scales)


def excluded_spread(
    physics: PhysicsModel, constant: FittedTerms, k: int, family: str, measured: Tensor, seed: int
) -> float | None:
    """The smallest spread of term ``k`` (the others constant) whose model the constant beats by two standard errors
    on ``measured``: a spread this wide is excluded by the data. None if none up to 2^8 times the first is."""
    centre = constant.priors[k].value
    baseline = discrepancies(physics, constant.candidates, constant.priors, measured, seed, SPREAD_REPEATS)
    size = max(abs(centre), (constant.scales or [0.0] * (k + 1))[k], 1e-12)

    def excluded(width: float) -> bool:
        priors: list[Prior] = [Constant(p.value) for p in constant.priors]
        priors[k] = prior(family, centre, width)
        return beats(baseline, discrepancies(physics, constant.candidates, priors, measured, seed, SPREAD_REPEATS))

    allowed, width = 0.0, FIRST_SPREAD * size
    for _ in range(SPREAD_DOUBLINGS):
        if excluded(width):
            break
        allowed, width = width, 2 * width
    else:
        return None
    for _ in range(SPREAD_BISECTIONS):
        middle = (allowed + width) / 2
        allowed, width = (allowed, middle) if excluded(middle) else (middle, width)
    return width
