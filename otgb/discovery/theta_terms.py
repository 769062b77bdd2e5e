"""Terms whose strength depends on theta, searched for where neither the named terms nor f_p's recalibrated priors
close the gap.

An effect can scale with a physics parameter: a friction that grows with a pendulum's frequency (``omega*velocity``),
a restoring force off by a fixed fraction (``omega^2*sin(angle)``). The library without theta holds no such term, and
a recalibration of theta's priors moves every term of f_p that theta enters, not one. So where the answer's model
(f_p, its priors recalibrated where that is the answer, plus the named terms) still disagrees with the validation
part by the disagreement map, the library search (:mod:`otgb.discovery.search`) runs again, on the answer's base:

- its candidates: each local library feature times each physics parameter and its square, for every component the
  answer's terms act on (all of f_p's acting components where none is named), beside the answer's own terms;
- its model replaces the answer's terms where it fits the validation part better than the answer by two standard
  errors (:func:`otgb.discovery.scores.beats`); its family is then chosen as any kept model's.

Where ``discover.theta_products`` already put such terms in the library, this step does not run.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from torch import Tensor

from otgb.discovery.answer import Answer, answer_fitting
from otgb.discovery.families import centre
from otgb.discovery.library import Candidate, feature_names, scaled_by_theta
from otgb.discovery.log import progress, short
from otgb.discovery.refine import FittedTerms, Fitting
from otgb.discovery.scores import Scores, beats, difference
from otgb.discovery.search import SearchStep, Unsupported, search
from otgb.discovery.stages import stage
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel
from otgb.physics.features import is_local

REASON = (
    "neither the named terms nor f_p's recalibrated priors close the gap (the answer still disagrees with the validation part)"
)


@dataclass(frozen=True)
class ThetaSearch:
    """The search on theta-dependent terms: why it ran, its path, the terms it dropped (intervals holding zero), and
    the model that replaces the answer's terms (None: the answer stays)."""

    reason: str
    steps: list[SearchStep] = field(default_factory=list)
    unsupported: list[Unsupported] = field(default_factory=list)
    kept: FittedTerms | None = None
    versus_answer: tuple[float, float] = (float("nan"), float("nan"))  # the answer's score minus the kept's, its SE


def theta_candidates(physics: PhysicsModel, components: list[str]) -> list[Candidate]:
    """Each local feature of ``physics``'s library times each physics parameter and its square, on ``components``."""
    local = [f for f in feature_names(physics) if is_local(f, physics)]
    return [Candidate(f, c) for c in components for f in scaled_by_theta(local, physics.theta_names, (1, 2))]


@stage("terms that scale with theta")
def theta_step(
    fitting: Fitting, answer: Answer, components: list[str], disagrees: Callable[[PhysicsModel, Tensor], bool]
) -> ThetaSearch | None:
    """The search on theta-dependent terms (the module docstring) on the answer's base, beside the answer's terms; None
    where f_p has no parameters or ``disagrees(model, validation)`` (the disagreement map of the answer's model) finds
    no remainder. ``components``: where to search when the answer names no term."""
    on_base = answer_fitting(fitting, answer)
    physics, terms = on_base.physics, answer.terms
    model = terms.model(physics) if terms is not None else Augmented(physics, [])
    if not physics.theta_names or not disagrees(model, on_base.val):
        return None
    named = [] if terms is None else list(terms.candidates)
    acting = list(dict.fromkeys(c.component for c in named)) or components
    candidates = [c for c in theta_candidates(physics, acting) if c not in named] + named
    init = [0.0] * (len(candidates) - len(named)) + ([centre(p) for p in terms.priors] if terms else [])
    progress(f"{REASON}: searching terms that scale with {', '.join(physics.theta_names)}")
    found, steps, unsupported = search(candidates, init, on_base, progress)
    scores = answer_scores(on_base, answer)
    if found is None or not beats(found.heldout, scores):
        progress("theta search: nothing better than the answer")
        return ThetaSearch(REASON, steps, unsupported)
    progress(f"theta search: kept {[c.feature for c in found.candidates]}, coefficients {short(found.priors)}")
    return ThetaSearch(REASON, steps, unsupported, found, difference(found.heldout, scores))


def answer_scores(on_base: Fitting, answer: Answer) -> Scores:
    """The answer's validation scores: its recalibration's where it holds one (beside terms: the two together's), else
    its terms', else f_p's alone."""
    if answer.recalibrated:
        return answer.recalibration.heldout
    if answer.terms is not None:
        return answer.terms.heldout
    if answer.recalibration is not None:
        return answer.recalibration.f_p_heldout
    return on_base.alone()
