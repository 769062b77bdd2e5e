"""The steps of discovery after its grey-box has learned (:func:`run`): name, add, verify.

Given f_p, measured trajectories and an OT grey-box trained on them ("Hybrid Generative Modeling
for Incomplete Physics: Deep Grey-Box Meets Optimal Transport"); the locate and learn steps before
these are :mod:`otgb.discovery.pipeline`'s:

3. **Name** (:mod:`otgb.discovery.naming`, :mod:`otgb.discovery.regression`): its correction f_phi,
   evaluated along generated trajectories, regressed on the candidate library
   (:mod:`otgb.discovery.library`).
4. **Cross-check and add** (:mod:`otgb.discovery.naming`, fits by :mod:`otgb.discovery.refine`):
   each strong candidate alone added to f_p with its coefficient fitted by distribution matching,
   ranked by the share of the gap it closes; the selected terms fitted together, each prior
   family tried, terms that do not lower the held-out energy dropped; the library search
   (:mod:`otgb.discovery.search`) where f_phi's route falls short.
5. **Verify** (:mod:`otgb.discovery.verify`): MMD, C2ST and energy distance on the held-out test
   measurements for f_p, the grey-box and the augmented physics next to the Reference (half the
   test measurements against the other half), and the disagreement map drawn again for the
   augmented physics.

The measured data are split by the data module (train / validation / test): locating and
fitting use the training part, choices between fitted models the validation part, the gap
table the test part.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from torch import Tensor

from otgb.discovery.after_fix import sentence_after
from otgb.discovery.answer import answer_fitting, answer_step
from otgb.discovery.draws import GREYBOX, acting_components, at_most, generated, simulate_candidate, simulate_from_priors
from otgb.discovery.forms import FormStep, form_step
from otgb.discovery.intervals import fitted_intervals
from otgb.discovery.locate import DisagreementMap, describe, locate
from otgb.discovery.log import DivergenceLog, progress, rounded, short
from otgb.discovery.naming import (
    MAX_FORWARD_TERMS,
    Naming,
    Weighed,
    add_step,
    cross_check_step,
    evidence_step,
    family_step,
    final_regression,
    fitting_for,
    name_step,
    strong_candidates,
)
from otgb.discovery.paired import PairedCheck
from otgb.discovery.record import Discovery
from otgb.discovery.refine import FittedTerms, Fitting
from otgb.discovery.scores import beats, difference, sample_scores
from otgb.discovery.search import SearchStep, Unsupported, search
from otgb.discovery.seeds import Seeds
from otgb.discovery.settings import Context, DiscoverySettings, Measurements
from otgb.discovery.stages import stage
from otgb.discovery.theta_terms import ThetaSearch, theta_step
from otgb.discovery.verdict import undertrained_text
from otgb.discovery.verify import closer_step, gap_step, paired_after
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel


@stage("disagreement map")
def locate_step(
    physics: PhysicsModel, measured: Tensor, settings: DiscoverySettings, context: Context, model_name: str = "f_p",
    paired: PairedCheck | None = None,
) -> DisagreementMap:  # fmt: skip
    """The disagreement map between ``measured`` (at most ``settings.tests.locate_rows`` of them, drawn at random) and as many
    trajectories of ``physics`` (f_p, or a candidate model whose diverged trajectories are dropped), with f_p's
    ``paired`` check on the measurements' inputs, if any."""
    seeds = context.seeds
    tests = settings.tests
    tested = at_most(measured, tests.locate_rows, seeds)
    simulate = simulate_candidate if isinstance(physics, Augmented) else simulate_from_priors
    simulated = simulate(physics, len(tested), seeds, model_name)
    result = locate(
        tested, simulated, physics.observation_times(), physics.observed,
        tests.n_permutations, tests.alpha, tests.regions_per_axis, seeds.root, paired,
    )  # fmt: skip
    return replace(result, drawn_from=len(measured) if len(tested) < len(measured) else 0)


def run(module: Any, data: Measurements, settings: DiscoverySettings, before: DisagreementMap, context: Context) -> Discovery:
    """Steps 3-5 on a trained grey-box ``module`` (a MapTraining), after a significant locate; a candidate model
    whose solve diverges is dropped where it diverged and listed in ``diverged``."""
    with DivergenceLog() as log:
        naming = name_step(module, settings, context.seeds)
        fitting = fitting_for(module.physics, data, settings, naming.designs, context)
        named = name_and_add(module, naming, fitting, settings, before, context, data.train_inputs is None)
        result = verify(named, module, data, settings, context, fitting, naming.designs)
    return replace(result, diverged=log.records)


def name_and_add(
    module: Any, naming: Naming, fitting: Fitting, settings: DiscoverySettings, before: DisagreementMap, context: Context,
    refit_x0: bool = True,
) -> Discovery:  # fmt: skip
    """From f_phi's regression ``naming``: cross-check the strong candidates, add along f_phi's route or the library
    search, weigh the evidence and choose the prior family, weigh a recalibration of f_p's priors (those of x0 too,
    with ``refit_x0``: the measurements do not record it); the record up to the verification."""
    physics, selections, designs = module.physics, naming.selections, naming.designs
    proposed = [f"{c.feature} on d{c.component}/dt: {v:.4g}" for c, v in naming.proposed]
    progress(
        f"f_phi's regression proposes {proposed}; each is checked against the measurements next"
        if proposed
        else "f_phi's regression proposes no term"
    )
    strong = strong_candidates(selections, designs, settings.library.strong_candidates)
    cross_check = cross_check_step(strong, fitting)
    progress(f"cross-checked {len(strong)} candidates alone")
    unused = undertrained(module, fitting.val, context.seeds)
    route = add_step(selections, designs, fitting) if proposed and unused is None else None
    if route is not None:
        progress(f"kept {[c.feature for c in route.kept.candidates]}, coefficients {short(route.kept.priors)}")
    kept, truncated = (route.kept, route.truncated) if route else (None, False)
    not_used = bool(proposed) and unused is not None  # f_phi proposed terms, but the grey-box is no evidence
    reason = search_reason(physics, kept, truncated, fitting.val, settings, context, not_used)
    searched = search_step(kept, reason, designs, fitting) if reason is not None else Searched(kept)
    dropped = [] if searched.replaced or route is None else route.dropped
    weighed, family, formed = None, None, None
    if searched.kept is not None:
        weighed = evidence_step(searched.kept, selections, cross_check, designs, fitting, settings.library.strong_candidates)
        formed = forms_step(weighed, designs, fitting, settings, context)
        family = family_step(formed.kept, fitting, settings.fits.families)
        dropped = dropped + family.dropped
        progress(f"fitted {family.choice.fitted.family} coefficients {short(family.choice.fitted.priors)}")
    terms = family.choice.fitted if family else None
    answer = answer_step(fitting, terms, settings, refit_x0)
    recalibration, recalibrated = answer.recalibration, answer.recalibrated
    if terms is not None and answer.terms is None:
        dropped = dropped + [{"feature": c.feature, "component": c.component} for c in terms.candidates]
        family, weighed = None, None
    terms, family = answer.terms, answer.family or family
    dropped = dropped + (answer.family.dropped if answer.family else [])
    disagrees = lambda model, val: locate_step(model, val, settings, context, "theta-check").any_significant  # noqa: E731
    theta = None if settings.library.theta_products else theta_step(fitting, answer, acting_components(physics), disagrees)
    if theta is not None and theta.kept is not None:
        family = family_step(theta.kept, answer_fitting(fitting, answer), settings.fits.families)
        dropped = dropped + family.dropped
        terms = family.choice.fitted
    return Discovery(
        before, describe(before), selections, cross_check, terms,
        family=family.choice if family else None, evidence=weighed.comparisons if weighed else [],
        added=weighed.added if weighed else [], dropped=dropped, correction_share=naming.correction_share,
        search=searched.steps, unsupported=searched.unsupported,
        route=route_name(searched, theta), search_reason=reason, undertrained=unused,
        recalibration=recalibration, recalibrated=recalibrated, forms=formed, theta_search=theta,
        evidence_on=fitting.evidence_on(),
    )  # fmt: skip


def route_name(searched: Searched, theta: ThetaSearch | None) -> str:
    """Which route named the kept terms."""
    if theta is not None and theta.kept is not None:
        return "library search on terms that scale with theta"
    return "library search" if searched.replaced else "f_phi regression"


@stage("parametric forms")
def forms_step(weighed: Weighed, designs: dict, fitting: Fitting, settings: DiscoverySettings, context: Context) -> FormStep:
    """The parametric forms weighed against the kept linear terms (:mod:`otgb.discovery.forms`), a remainder
    checked by the disagreement map of the kept model on the validation part."""

    def remainder() -> bool:
        model = weighed.kept.model(fitting.physics)
        return locate_step(model, fitting.val, settings, context, "augmented-check").any_significant

    return form_step(weighed.kept, weighed.comparisons, designs, fitting, list(settings.fits.forms), remainder)


def verify(
    named: Discovery, module: Any, data: Measurements, settings: DiscoverySettings, context: Context, fitting: Fitting,
    designs: dict,
) -> Discovery:  # fmt: skip
    """On the test part, which no fit saw: the gap table of f_p, the grey-box and the augmented physics, and for named
    terms their intervals, the disagreement maps before and after, the paired check and the test of which is nearer."""
    physics, n, seeds = module.physics, len(data.test), context.seeds
    if named.recalibrated and named.found:  # the terms were fitted on f_p with its recalibrated priors
        fitting = replace(fitting, physics=named.recalibration.physics)
    sources = {"f_p": simulate_from_priors(physics, n, seeds, "gap-f_p"), "greybox": generated(module, n, seeds)}
    found: dict[str, Any] = {}
    if named.found:
        found["final_terms"] = final_regression(named.selections, designs, named.fitted.candidates, settings, seeds)
        found["intervals"] = fitted_intervals(fitting, named.fitted)
        shown = rounded(found["intervals"].centre) if found["intervals"] else "none (the fit is not at a minimum)"
        progress(f"intervals: {shown}")
    if named.found:
        found["paired_after"] = paired_after(named.fitted, physics, data, settings.tests.alpha)
    return verify_answer(replace(named, **found), physics, data.test, settings, context, sources)


@stage("verification on the test part")
def verify_answer(
    named: Discovery, physics: PhysicsModel, test: Tensor, settings: DiscoverySettings, context: Context, sources: dict
) -> Discovery:  # fmt: skip
    """On the ``test`` part: the gap table of ``sources`` and, where the answer changes f_p, of its model, the
    disagreement maps of f_p and of that model, and the test of which is nearer."""
    found: dict[str, Any] = {}
    if named.explained:  # each solve gets a model of its own, as each counts its solves (otgb.physics.solvers)
        sources = {**sources, "augmented": simulate_candidate(named.model(physics), len(test), context.seeds, "gap-augmented")}
        found["before_on_test"] = locate_step(physics, test, settings, context, "f_p-test")
        found["after"] = locate_step(named.model(physics), test, settings, context, "augmented")
    progress("verifying on the test part")
    result = replace(named, gap=gap_step(sources, test, settings, context.seeds), draws=sources, **found)
    if not result.explained:
        return result
    result = replace(result, closer=closer_step(result.model(physics), physics, test, settings, context.seeds))
    return replace(result, sentence_after=sentence_after(result))


def search_reason(
    physics: PhysicsModel, kept: FittedTerms | None, truncated: bool, val: Tensor, settings: DiscoverySettings,
    context: Context, unused: bool,
) -> str | None:  # fmt: skip
    """Why the library search runs, or None: f_phi's terms were not used (``unused``: an undertrained grey-box), its
    route named nothing, was truncated (:func:`add_step`), terms fixed in space were asked for (a correction network
    that convolves over the field hardly shows them), or the physics it augmented still disagrees with the validation
    measurements."""
    if kept is None:
        return (
            "the grey-box does not beat f_p alone by two standard errors, so f_phi's terms are not used"
            if unused
            else "f_phi named nothing"
        )
    if truncated:
        return f"f_phi's route reached {MAX_FORWARD_TERMS} terms and was cut short"
    if settings.library.position_degree and getattr(physics, "coordinate_names", ()):
        return (
            "terms fixed in space were asked for (discover.position_degree), so they are searched for directly, "
            "not only along f_phi's route"
        )
    if locate_step(kept.model(physics), val, settings, context, "augmented-check").any_significant:
        return "the physics augmented along f_phi's route still disagrees with the validation measurements"
    return None


@dataclass(frozen=True)
class Searched:
    """What the library search gave: the constant fit kept, whether its model replaced f_phi's, its path and the terms
    it dropped because their intervals hold zero."""

    kept: FittedTerms | None
    replaced: bool = False
    steps: list[SearchStep] = field(default_factory=list)
    unsupported: list[Unsupported] = field(default_factory=list)


@stage("library search")
def search_step(kept: FittedTerms | None, reason: str, designs: dict, fitting: Fitting) -> Searched:
    """The library search (:mod:`otgb.discovery.search`), run for ``reason``; its model replaces ``kept`` as
    :func:`replaces` says."""
    progress(f"{reason}: searching the local library")
    candidates = [c for design in designs.values() for c in design.candidates]
    current = {} if kept is None else {c: p.value for c, p in zip(kept.candidates, kept.priors)}
    init = [current.get(c, 0.0) for c in candidates]
    found, steps, unsupported = search(candidates, init, fitting, progress)
    if found is None or (kept is not None and not replaces(found, kept)):
        progress("search: nothing better than " + ("f_phi's terms" if kept else "f_p alone"))
        return Searched(kept, False, steps, unsupported)
    progress(f"search: kept {[c.feature for c in found.candidates]}, coefficients {short(found.priors)}")
    return Searched(found, True, steps, unsupported)


def replaces(found: FittedTerms, kept: FittedTerms) -> bool:
    """Whether the search's model replaces f_phi's: it fits the validation part better by two standard errors, or
    f_phi's model does not fit better by two and the search's has fewer terms (the sparser of two models the data
    cannot tell apart, the rule of every other step) or as many with a lower discrepancy (of two as sparse, the
    nearer: f_phi's route ranks terms by how its correction network uses them, which can miss a term it hardly
    shows, such as one fixed in space)."""
    if beats(found.heldout, kept.heldout):
        return True
    if beats(kept.heldout, found.heldout):
        return False
    size, kept_size = len(found.candidates), len(kept.candidates)
    other_terms = set(found.candidates) != set(kept.candidates)  # the same terms refitted: a tie, f_phi's stays
    nearer = kept.heldout.mean - found.heldout.mean > 1e-9 * abs(kept.heldout.mean)  # beyond float rounding
    return size < kept_size or (size == kept_size and other_terms and nearer)


UNDERTRAINED_REPEATS = 5  # simulation draws per held-out score of the grey-box and of f_p
UNDERTRAINED_DRAWS = 256  # simulated trajectories per draw, at least: a draw as small as a small validation part is noise


def undertrained(module: Any, heldout: Tensor, seeds: Seeds) -> dict[str, float] | None:
    """The grey-box's and f_p's held-out discrepancy when the grey-box does not beat f_p by two standard errors
    (:func:`otgb.discovery.scores.beats`): its correction is then no evidence, and the naming relies on the
    library search. None when the grey-box is better.

    Both are simulated from the same inputs (x0, theta) in each draw (common random numbers), so their scores differ
    by the correction, not by the luck of the draws; what the few validation trajectories leave uncertain remains.
    """
    physics = module.physics
    n, m = len(heldout), max(len(heldout), UNDERTRAINED_DRAWS)
    greybox = sample_scores(lambda r: generated(module, m, seeds.undertrained_draw(r)), heldout, UNDERTRAINED_REPEATS)
    draw_f_p = lambda r: simulate_from_priors(physics, m, seeds.undertrained_draw(r), GREYBOX)  # noqa: E731
    alone = sample_scores(draw_f_p, heldout, UNDERTRAINED_REPEATS)
    if beats(greybox, alone):
        return None
    gain, error = difference(greybox, alone)
    progress(f"the OT grey-box {undertrained_text(gain, error, n, greybox.mean, alone.mean)}")
    return {
        "greybox_heldout_energy": greybox.mean, "f_p_heldout_energy": alone.mean,
        "difference": gain, "standard_error": error, "validation_trajectories": n,
    }  # fmt: skip
