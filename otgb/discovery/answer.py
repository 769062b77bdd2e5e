"""The answer of discovery's add step: f_p plus the named terms, f_p with its priors recalibrated, or both.

A physicist's first question about a model that disagrees with measurements is whether its form or its parameters are
wrong. f_p's priors of theta (and of x0 where the measurements do not record it) are refitted by distribution matching
(:mod:`otgb.discovery.recalibration`) and weighed against f_p alone and against the named terms by held-out evidence
(:func:`otgb.discovery.scores.beats`); where terms are named and the recalibration alone is not the answer, the two
together are fitted and weighed against each.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

from torch import Tensor

from otgb.discovery.crossfit import cross_fitted, refit_steps
from otgb.discovery.families import centre
from otgb.discovery.log import progress
from otgb.discovery.naming import FamilyStep, family_step
from otgb.discovery.recalibration import Recalibration, recalibrate
from otgb.discovery.refine import FittedTerms, Fitting, refit_on
from otgb.discovery.scores import HELDOUT_REPEATS, Scores, beats, difference
from otgb.discovery.settings import DiscoverySettings
from otgb.discovery.stages import stage


@dataclass(frozen=True)
class Answer:
    """f_p's recalibration (None: not tried or nothing to refit), whether the answer holds it, and the terms the
    answer holds (None: none, or set aside for the recalibration)."""

    recalibration: Recalibration | None
    recalibrated: bool
    terms: FittedTerms | None
    family: FamilyStep | None = None  # the terms' prior family chosen again beside the recalibration (None: as before)


def answer_step(fitting: Fitting, terms: FittedTerms | None, settings: DiscoverySettings, refit_x0: bool) -> Answer:
    """Terms, recalibrated priors or both: f_p's priors refitted (:func:`recalibrate_step`) and weighed against f_p
    alone and the terms (:func:`answers_instead`); where terms are named and the recalibration is not the answer, the
    two together (:func:`both_step`): a prior refitted alone can move the wrong way to mimic a missing term."""
    recalibration = recalibrate_step(fitting, refit_x0) if settings.fits.recalibrate else None
    if recalibration is None:
        return Answer(None, False, terms)
    if answers_instead(recalibration, terms):
        if terms is not None:
            better = f"the recalibrated f_p fits {fitting.heldout_part} better than f_p plus the terms"
            progress(f"{better}: the terms are set aside")
        return Answer(recalibration, True, None)
    both = both_step(fitting, recalibration, terms, settings.fits.families, refit_x0) if terms is not None else None
    return Answer(both[0], True, both[1].choice.fitted, both[1]) if both else Answer(recalibration, False, terms)


@stage("terms and recalibration together")
def both_step(
    fitting: Fitting, alone: Recalibration, terms: FittedTerms, families: tuple[str, ...], refit_x0: bool
) -> tuple[Recalibration, FamilyStep] | None:
    """f_p's priors refitted with the named terms in (their coefficients' priors held), then the terms refitted on f_p
    with those priors, their prior family chosen again (a spread can have stood in for the priors' error): the
    recalibration (its scores those of the two together) and the terms' family step, where the two together fit the
    validation part better than the terms alone and than the recalibration alone, by two standard errors each; else
    None."""
    data = (fitting.train, fitting.val, fitting.steps, fitting.batch, fitting.seed, fitting.spread_samples)
    beside = recalibrate(terms.model(fitting.physics), *data, states=refit_x0)  # its own scores are not used
    if beside is None:
        return None
    base = beside.physics.base
    on_base = replace(fitting, physics=base)
    constant = on_base(terms.candidates, [centre(p) for p in terms.priors], natural_scales=False)
    family = family_step(constant, on_base, families)
    together = family.choice.fitted
    if fitting.folds is not None:  # both refitted on each fold's complement, not the terms alone on the priors' fit
        on_folds = both_on_fold(fitting, terms, together, beside, refit_x0)
        together = replace(together, heldout=cross_fitted(fitting.folds, on_folds))
    better, error = difference(together.heldout, terms.heldout)
    progress(f"f_p's priors recalibrated beside the terms: {better:+.3g} +- {error:.2g} below the terms alone")
    if not (beats(together.heldout, terms.heldout) and beats(together.heldout, alone.heldout)):
        return None
    both = replace(beside, physics=base, heldout=together.heldout, f_p_heldout=alone.f_p_heldout)  # against f_p alone
    return both, family


def both_on_fold(
    fitting: Fitting, terms: FittedTerms, together: FittedTerms, beside: Recalibration, refit_x0: bool
) -> Callable[[int, Tensor, Tensor], Scores]:
    """The two together fitted again on a fold's complement as on the training part (f_p's priors refitted beside the
    named ``terms`` held at that fold's own refit of them, then the terms on those priors), each refit started where its
    fit on the training part ended (``beside``'s priors, ``together``'s terms), scored on the fold:
    :func:`otgb.discovery.crossfit.cross_fitted`'s step."""

    def score_fold(k: int, rest: Tensor, held_out: Tensor) -> Scores:
        held = replace(terms, priors=terms.fold_priors[k]) if terms.fold_priors else terms
        data = (rest, held_out, refit_steps(fitting.steps), fitting.batch, fitting.seed, fitting.spread_samples)
        options = {"states": refit_x0, "with_intervals": False, "ended": beside.ended}
        again = recalibrate(held.model(fitting.physics), *data, **options)
        if again is None:
            return Scores.diverged(HELDOUT_REPEATS)
        return refit_on(again.physics.base, together, rest, held_out, fitting).heldout

    return score_fold


def answers_instead(recalibration: Recalibration, terms: FittedTerms | None) -> bool:
    """Whether f_p with recalibrated priors is the answer: it fits the validation part better than f_p alone by two
    standard errors, and better than f_p plus the named terms (if any) by two. Where neither of those two beats the
    other, the terms stay and the verdict says that the measurements cannot tell them from a recalibration."""
    return recalibration.beats_f_p and (terms is None or beats(recalibration.heldout, terms.heldout))


@stage("recalibration")
def recalibrate_step(fitting: Fitting, refit_x0: bool) -> Recalibration | None:
    """f_p's theta priors (and x0's, with ``refit_x0``) refitted to the training part and scored on the validation part
    (:mod:`otgb.discovery.recalibration`)."""
    data = (fitting.train, fitting.val, fitting.steps, fitting.batch, fitting.seed, fitting.spread_samples)
    recalibration = recalibrate(fitting.physics, *data, states=refit_x0, folds=fitting.folds)
    if recalibration is not None:
        below, error = recalibration.below_f_p
        priors = ", ".join(f"{r.parameter} {r.prior!r}" for r in recalibration.parameters)
        progress(f"recalibrated f_p's priors: {priors}; {below:+.3g} +- {error:.2g} below f_p alone on {fitting.heldout_part}")
    return recalibration


def answer_fitting(fitting: Fitting, answer: Answer) -> Fitting:
    """``fitting`` on the answer's base: f_p with its recalibrated priors where the answer holds them."""
    return replace(fitting, physics=answer.recalibration.physics) if answer.recalibrated else fitting
