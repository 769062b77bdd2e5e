"""The steps that name and add terms: f_phi's regression on the library, the cross-check of strong candidates, the
forward route with its pruning, the evidence against alternatives and the prior family."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from torch import Tensor

from otgb.discovery.crossfit import Folds
from otgb.discovery.draws import acting_components, at_most, greybox_draws
from otgb.discovery.evidence import Comparison, moves_with, weigh
from otgb.discovery.families import centre, varies
from otgb.discovery.intervals import Intervals, fitted_intervals
from otgb.discovery.library import Candidate, build_library
from otgb.discovery.log import progress
from otgb.discovery.refine import FittedTerms, Fitting
from otgb.discovery.regression import Selection, describe_terms, design_matrix, regress, subset_coefficients
from otgb.discovery.scores import beats, difference
from otgb.discovery.seeds import Seeds
from otgb.discovery.settings import Context, DiscoverySettings, Measurements
from otgb.discovery.stages import stage
from otgb.discovery.variation import FamilyChoice
from otgb.discovery.variation import choose_prior as choose_family_of
from otgb.physics.base import PhysicsModel


@dataclass(frozen=True)
class Naming:
    """f_phi's regression on the library: per acting component its selection and its design, the grey-box's draws
    along which f_phi was evaluated, and the share |f_phi| / |f_p| (RMS) along them."""

    selections: list[Selection]
    designs: dict
    draws: dict[str, Tensor]
    correction_share: float

    @property
    def proposed(self) -> list[tuple[Candidate, float]]:
        """The selected terms with their slopes on f_phi."""
        return [(t.candidate, t.coefficient) for s in self.selections for t in s.terms]


@stage("f_phi regression")
def name_step(module: Any, settings: DiscoverySettings, seeds: Seeds) -> Naming:
    """Regress f_phi on the library, per component."""
    physics = module.physics
    library = settings.library
    draws = greybox_draws(module, library.n_trajectories, seeds)
    selections, designs = [], {}
    for component in acting_components(physics):
        index = physics.state_names.index(component)
        candidates = build_library(physics, [component], library.theta_products, library.position_degree)
        target = draws["correction"][:, :, index]
        design = design_matrix(physics, candidates, draws["states"], draws["theta"], target, seeds.root, draws.get("inputs"))
        selections.append(regress(design, component, library.n_bootstrap, seeds.root))
        designs[component] = design
    share = float(draws["correction"].pow(2).mean().sqrt() / draws["physics"].pow(2).mean().sqrt().clamp_min(1e-12))
    return Naming(selections, designs, draws, share)


def strong_candidates(selections: list[Selection], designs: dict, k: int) -> list[tuple]:
    """(candidate, its slope alone) to cross-check: the k largest selected terms and their alternatives,
    and per component the k candidates that alone explain most of f_phi."""
    chosen: list[Candidate] = []
    for term in sorted((t for s in selections for t in s.terms), key=lambda t: -t.size)[:k]:
        chosen += [term.candidate, *term.alternatives]
    slopes = {}
    for design in designs.values():
        X, y = design.X, design.y
        slope = (X * y[:, None]).sum(0) / (X**2).sum(0).clip(1e-300)
        r2 = 1 - ((y[:, None] - X * slope) ** 2).sum(0) / max((y**2).sum(), 1e-300)
        slopes.update({c: float(b) for c, b in zip(design.candidates, slope)})
        chosen += [design.candidates[j] for j in r2.argsort()[::-1][:k]]
    return [(c, slopes[c]) for c in dict.fromkeys(chosen)]


@stage("cross-check")
def cross_check_step(strong: list[tuple], fitting: Fitting) -> list[dict]:
    """Each strong candidate alone added to f_p, its coefficient fitted: the share of f_p's held-out gap it closes,
    and how far below f_p alone's its held-out energy lies, with that difference's standard error."""
    baseline = fitting.alone()
    gap = baseline.mean
    rows = []
    for candidate, init in strong:
        fitted = fitting([candidate], [init])
        below, error = difference(fitted.heldout, baseline)
        rows.append(
            {
                "feature": candidate.feature,
                "component": candidate.component,
                "coefficient": fitted.priors[0].value,
                "heldout_energy": fitted.heldout_energy,
                "gap_closed": 1 - fitted.heldout_energy / gap if gap > 0 else 0.0,
                "below_f_p": below,
                "standard_error": error,
            }
        )
    return sorted(rows, key=lambda r: -r["gap_closed"])


def fitting_for(
    physics: PhysicsModel, data: Measurements, settings: DiscoverySettings, designs: dict, context: Context
) -> Fitting:
    """The run's :class:`otgb.discovery.refine.Fitting`: the settings' steps, batch and seed, and each library
    candidate's natural scale, the slope at which its term alone would be as large as f_phi on its component."""
    natural = {c: _natural_scale(c, design) for design in designs.values() for c in design.candidates}
    train, val = (at_most(part, settings.fits.score_rows, context.seeds) for part in (data.train, data.val))
    steps = (settings.fits.steps, settings.fits.batch, context.seeds.root)
    fits = {"cache": context.cache, "device": context.device, "spread_samples": settings.fits.spread_samples}
    folds = Folds.of(train, val, settings.fits.folds, context.seeds.root)
    return Fitting(physics, train, val, *steps, natural, folds=folds, **fits)


def _natural_scale(candidate: Candidate, design: Any) -> float:
    index = design.candidates.index(candidate)
    return float(np.sqrt((design.y**2).mean()) / max(design.scale[index], 1e-12))


MAX_FORWARD_TERMS = 6  # models on f_phi's route at most (its prune refits O(k^2) models)


def _on(candidate: Candidate) -> str:
    return f"{candidate.feature} on d{candidate.component}/dt"


@dataclass(frozen=True)
class Route:
    """The terms kept along f_phi's route (their constant fit), those it left out, and whether it was cut short."""

    kept: FittedTerms
    dropped: list[dict]
    truncated: bool


@stage("f_phi route fits")
def add_step(selections: list[Selection], designs: dict, fitting: Fitting) -> Route:
    """Forward selection on held-out measurements, then the prior family.

    The selected terms are ordered by the size of their contribution to f_phi; the models made
    of the first 1, 2, ... of them (coefficients started at their least-squares values and
    fitted by distribution matching) are scored on the validation measurements. The path
    stops after two models in a row that do not beat the leader (the last model that beat the
    leader before it) by two standard errors: f_phi's regression may select many small terms, each
    lowering the held-out score a little (reaction-diffusion). It stops at ``MAX_FORWARD_TERMS``
    terms: a correction whose named terms need more to match the measurements learned an average
    rather than a shape; the route is then *truncated* and the library search (which tries every
    subset) runs. The sparsest model that the best
    does not beat by more than two standard errors is kept, then pruned backwards (:func:`prune`);
    the terms left out are reported as dropped.
    """
    ordered = sorted(((t.size, t.candidate) for s in selections for t in s.terms), key=lambda pair: -pair[0])
    path = [c for _, c in ordered]
    fits: list[FittedTerms] = []
    leader, truncated = 0, False  # leader: the last model that beat the leader before it
    for k in range(1, len(path) + 1):
        if k > MAX_FORWARD_TERMS:
            truncated = True
            break
        init = _initial(path[:k], designs)
        fits.append(fitting(path[:k], init))
        progress(f"{k} term(s) {[_on(c) for c in path[:k]]}: held-out energy {fits[-1].heldout_energy:.4g}")
        if beats(fits[-1].heldout, fits[leader].heldout):
            leader = k - 1
        elif k - 1 - leader >= 2:
            break
    best = min(fits, key=lambda f: f.heldout_energy)
    current = prune(next(f for f in fits if not beats(best.heldout, f.heldout)), fitting)
    dropped = [{"feature": c.feature, "component": c.component} for c in path if c not in current.candidates]
    return Route(current, dropped, truncated)


@dataclass(frozen=True)
class Weighed:
    """The kept terms after the evidence step: their fit, their comparisons with the alternatives and the strong
    candidates it added."""

    kept: FittedTerms
    comparisons: list[Comparison]
    added: list[dict]


@stage("evidence")
def evidence_step(
    kept: FittedTerms, selections: list[Selection], cross_check: list[dict], designs: dict, fitting: Fitting, per_term: int
) -> Weighed:  # fmt: skip
    """The kept terms against every single-term swap among the ``cross_check``'s strong candidates, the terms each moves with in
    its regression and Coulomb friction, on the validation measurements (:mod:`otgb.discovery.evidence`); a swap that
    fits better by two standard errors is taken, and an added strong candidate that does so with a coefficient whose
    95 % interval excludes zero."""

    def start(candidate: Candidate) -> float:
        return _initial([candidate], designs)[0]

    def interval(fitted: FittedTerms) -> tuple[float, float] | None:
        intervals = fitted_intervals(fitting, fitted)
        return None if intervals is None else intervals.centre[-1]

    partners = moves_with(selections)
    kept, comparisons, added = weigh(fitting.physics, kept, cross_check, per_term, fitting, start, interval, partners)
    for c in comparisons:
        margin = f"{c.standard_errors:+.1f} standard errors" if math.isfinite(c.difference) else "the swapped model diverges"
        progress(f"evidence: {c.replaced.feature} against {c.by.feature}: {margin}")
    return Weighed(kept, comparisons, added)


def choose_prior(constant: FittedTerms, fitting: Fitting, families: tuple[str, ...]) -> FamilyChoice:
    """Each prior family of ``families`` for the constant fit's terms, fitted from its optimum on
    ``discover.spread_samples`` simulated samples (the constant too, so that the families differ by
    their spread, not by how many draws placed their centres); the choice as :mod:`otgb.discovery.variation` makes it."""
    start = [p.value for p in constant.priors]

    def refit(family: str) -> FittedTerms:
        return fitting(constant.candidates, start, family, natural_scales=False, samples=fitting.spread_samples)

    def interval(fitted: FittedTerms) -> Intervals | None:
        return fitted_intervals(fitting, fitted)

    options = {"interval": interval, "cross_fitted": fitting.folds is not None}
    return choose_family_of(fitting.physics, constant, fitting.train, families, refit, fitting.seed, **options)


def prune(current: FittedTerms, fitting: Fitting) -> FittedTerms:
    """Backward elimination: drop a kept term while the model without it is not beaten on held-out data.

    The forward order comes from f_phi; the measurements may need a later term instead of an
    earlier one (a network that learned drag as a mostly linear friction ranks velocity first):
    the model without the earlier term then fits as well and the term goes. The reduced models are
    fitted in ``current``'s prior family, started at its centres.
    """
    while len(current.candidates) > 1:
        trials = []
        for k in range(len(current.candidates)):
            keep = [i for i in range(len(current.candidates)) if i != k]
            init = [centre(current.priors[i]) for i in keep]
            trials.append(fitting([current.candidates[i] for i in keep], init, current.family, natural_scales=False))
        reduced = min(trials, key=lambda f: f.heldout_energy)
        if beats(current.heldout, reduced.heldout):
            return current
        progress(
            f"dropped {[_on(c) for c in current.candidates if c not in reduced.candidates]}: not needed by the held-out data"
        )
        current = reduced
    return current


@dataclass(frozen=True)
class FamilyStep:
    """The prior family chosen for the kept terms, and the terms dropped once they were fitted in it."""

    choice: FamilyChoice
    dropped: list[dict]


@stage("prior family")
def family_step(kept: FittedTerms, fitting: Fitting, families: tuple[str, ...]) -> FamilyStep:
    """The prior family of ``kept``'s terms (:func:`choose_prior`); when it varies, or when a family that varies
    scored best but its spread had no interval, the terms are pruned again in that family.

    Every earlier step fits constant coefficients. When the effect varies between trajectories, a
    constant one misfits the measurements, and a further term can lower the held-out discrepancy by
    taking up part of the variation (on the one-to-many pendulum, whose friction is one of two values,
    Coulomb friction was added beside viscous friction). Fitted with the chosen family, such a term is
    no longer needed: it is dropped (:func:`prune`) and the family is chosen again for the terms left.
    Such a term can also leave the varying fit without a minimum the sandwich can use (SciPy pendulums
    whose viscous friction varied as U(-1.5, -0.5): Coulomb friction -0.02 beside it, the uniform family
    7 standard errors better than the constant, refused for want of an interval): the family's fit is then
    pruned as well.
    """
    choice = choose_prior(kept, fitting, families)
    varying = choice.fitted if varies(choice.fitted.family) else choice.rejected_fit
    if varying is None or len(kept.candidates) == 1:
        return FamilyStep(choice, [])
    pruned = prune(varying, fitting)
    if len(pruned.candidates) == len(kept.candidates):
        return FamilyStep(choice, [])
    dropped = [{"feature": c.feature, "component": c.component} for c in kept.candidates if c not in pruned.candidates]
    constant = fitting(pruned.candidates, [centre(p) for p in pruned.priors], natural_scales=False)
    return FamilyStep(choose_prior(constant, fitting, families), dropped)


@stage("f_phi regression")
def final_regression(
    selections: list[Selection], designs: dict, kept: list[Candidate], settings: DiscoverySettings, seeds: Seeds
) -> list:
    """The regression of f_phi on the kept terms alone, per component (intervals, shares, ambiguity)."""
    terms = []
    for selection in selections:
        design = designs[selection.component]
        mine = [c for c in kept if c.component == selection.component and c in design.candidates]  # not a form
        if mine:
            inclusion = {Candidate(f, selection.component): p for f, p in selection.inclusion.items()}
            terms += describe_terms(design, mine, inclusion, settings.library.n_bootstrap, seeds.root)
    return terms


def _initial(candidates: list[Candidate], designs: dict) -> list[float]:
    """Least-squares starting values per component for ``candidates``."""
    values = {}
    for component in dict.fromkeys(c.component for c in candidates):
        mine = [c for c in candidates if c.component == component]
        values.update(zip(mine, subset_coefficients(designs[component], mine)))
    return [values[c] for c in candidates]
