"""The record of a discovery run's steps, from which the verdict (:mod:`otgb.discovery.verdict`) and the report's
files are made."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

from otgb.discovery.closer import Closeness
from otgb.discovery.evidence import Comparison
from otgb.discovery.forms import FormStep
from otgb.discovery.intervals import Intervals
from otgb.discovery.locate import DisagreementMap
from otgb.discovery.paired import PairedCheck
from otgb.discovery.recalibration import Recalibration
from otgb.discovery.refine import FittedTerms
from otgb.discovery.regression import SelectedTerm, Selection
from otgb.discovery.search import SearchStep, Unsupported
from otgb.discovery.theta_terms import ThetaSearch
from otgb.discovery.variation import FamilyChoice
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel


@dataclass(frozen=True)
class Discovery:
    """Everything the report shows: each step's result, written once where the step returns it."""

    before: DisagreementMap
    sentence_before: str
    selections: list[Selection] = field(default_factory=list)
    cross_check: list[dict] = field(default_factory=list)
    fitted: FittedTerms | None = None
    final_terms: list[SelectedTerm] = field(default_factory=list)  # the regression on f_phi of the kept terms
    intervals: Intervals | None = None  # of the fitted coefficients (and spreads), :mod:`otgb.discovery.intervals`
    family: FamilyChoice | None = None  # the prior family's choice and its evidence (otgb.discovery.variation)
    evidence: list[Comparison] = field(default_factory=list)  # the kept terms against their alternatives (.evidence)
    added: list[dict] = field(default_factory=list)  # strong candidates the evidence step added (.evidence)
    dropped: list[dict] = field(default_factory=list)
    before_on_test: DisagreementMap | None = None  # f_p on the test part: what ``after`` is compared with
    after: DisagreementMap | None = None
    sentence_after: str | None = None
    paired_after: PairedCheck | None = None  # constant named terms on the test part's recorded inputs (.paired)
    gap: dict[str, dict[str, float]] = field(default_factory=dict)
    closer: Closeness | None = None  # whether the augmented physics is nearer to the test part than f_p (.closer)
    correction_share: float | None = None
    pointwise: dict[str, dict[str, float]] = field(default_factory=dict)  # against a known DGP (otgb.discovery.known)
    draws: dict[str, Tensor] = field(default_factory=dict)  # the gap table's samples, as many as the test part
    search: list[SearchStep] = field(default_factory=list)  # the library search's path, when it ran
    unsupported: list[Unsupported] = field(default_factory=list)  # terms dropped from its model: intervals hold zero
    route: str = "f_phi regression"  # which route named the kept terms
    search_reason: str | None = None  # why the library search ran (None: it did not)
    diverged: list[dict] = field(default_factory=list)  # solves that diverged, per step and model (otgb.discovery.log)
    undertrained: dict[str, float] | None = None  # the grey-box's and f_p's held-out energy when it is no better
    recalibration: Recalibration | None = None  # f_p's theta priors refitted (otgb.discovery.recalibration)
    recalibrated: bool = False  # whether the answer holds f_p with those priors (alone, or beneath the named terms)
    forms: FormStep | None = None  # the parametric forms weighed against the linear terms (otgb.discovery.forms)
    theta_search: ThetaSearch | None = None  # terms that scale with theta, searched where the answer left a remainder
    evidence_on: str | None = None  # what the held-out scores of its decisions are cross-fitted over (None: not)

    @property
    def found(self) -> bool:
        """Whether terms were named."""
        return self.fitted is not None and len(self.fitted.candidates) > 0

    @property
    def explained(self) -> bool:
        """Whether the answer changes f_p: terms named, or its priors recalibrated."""
        return self.found or self.recalibrated

    def model(self, physics: PhysicsModel) -> Augmented:
        """The answer's model: f_p (its priors recalibrated where that is the answer) plus the named terms."""
        base = self.recalibration.physics if self.recalibrated else physics
        return self.fitted.model(base) if self.found else Augmented(base, [])
