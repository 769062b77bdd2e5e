"""The missing-effect discovery workflow: locate, learn, name, add, verify.

Given f_p, a file of measured trajectories and an OT grey-box trained on them ("Hybrid
Generative Modeling for Incomplete Physics: Deep Grey-Box Meets Optimal Transport"):

1. **Locate** (:mod:`otgb.discovery.locate`): where and when f_p's simulations and the
   measured training trajectories disagree. Nothing significant: no missing effect detected.
2. **Learn**: the grey-box T_phi (trained by ``otgb discover`` or loaded from a checkpoint).
3. **Name** (:mod:`otgb.discovery.regression`): its correction f_phi, evaluated along generated
   trajectories, regressed on the candidate library (:mod:`otgb.discovery.library`).
4. **Cross-check and add** (:mod:`otgb.discovery.refine`): each strong candidate alone added
   to f_p with its coefficient fitted by distribution matching, ranked by the share of the gap
   it closes; the selected terms fitted together, each prior family tried, terms that do not
   lower the held-out energy dropped.
5. **Verify**: MMD, C2ST and energy distance on the held-out test measurements for f_p, the
   grey-box and the augmented physics next to the Reference (half the test measurements
   against the other half), and the disagreement map drawn again for the augmented physics.

The measured data are split by the data module (train / validation / test): locating and
fitting use the training part, choices between fitted models the validation part, the gap
table the test part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from otgb.data.measured import CHUNK, simulate_in_chunks
from otgb.data.seeding import generator_for
from otgb.discovery.closer import Closeness, closer
from otgb.discovery.evidence import Comparison, moves_with, weigh
from otgb.discovery.fit_cache import FitCache
from otgb.discovery.intervals import Intervals, fitted_intervals
from otgb.discovery.library import MAX_DEGREE, Candidate, build_library, physical_name
from otgb.discovery.locate import DisagreementMap, describe, locate
from otgb.discovery.log import DivergenceLog, diverged, progress, rounded, short
from otgb.discovery.paired import PairedCheck, paired_check
from otgb.discovery.refine import (
    FAMILIES,
    FittedTerms,
    Fitting,
    beats,
    centre,
    difference,
    discrepancies,
    sample_scores,
    simulate_finite,
    term_names,
)
from otgb.discovery.regression import SelectedTerm, Selection, describe_terms, design_matrix, regress, subset_coefficients
from otgb.discovery.search import SearchStep, Unsupported, search
from otgb.discovery.variation import FamilyChoice
from otgb.discovery.variation import choose_prior as choose_family_of
from otgb.errors import InputError
from otgb.metrics.c2st import c2st
from otgb.metrics.energy import energy_distance
from otgb.metrics.mmd import mmd_multiscale
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel


class DiscoverySettings:
    """Settings of ``otgb discover`` (the ``discover:`` section of its config).

    Args:
        n_permutations: Label permutations per p-value of the disagreement map and of the test of which model is nearer.
        alpha: False discovery rate of the disagreement map (Benjamini-Hochberg), and the level of the paired check and of
            the test of whether the augmented physics is nearer to the test part than f_p alone.
        regions_per_axis: Blocks per spatial axis in which a field's cells are compared.
        locate_rows: Most measured trajectories in a disagreement map (a random subset beyond, drawn with ``seed``),
            and as many simulated: the permutation tests' time and memory grow with the square of the rows.
        score_rows: Most measured trajectories of the training and validation parts that the coefficient fits and the
            scores of fits, prior families and spreads use (a random subset beyond): each score grows with the square.
        n_trajectories: Generated trajectories along which the correction f_phi is evaluated.
        n_bootstrap: Bootstrap resamples (of f_phi's trajectories) for inclusion probabilities and f_phi's slope intervals.
        theta_products: Whether the library also offers each feature times each physics parameter.
        position_degree: On a field, the library also offers the grid's coordinates (``s``; ``x``, ``y``) and their
            products and powers up to this degree, as terms fixed in space (a heater, a sink); 0: none.
        strong_candidates: Candidates per component cross-checked alone (besides the selected ones), by univariate R^2.
        fit_steps: L-BFGS iterations of each distribution-matching fit of coefficients.
        fit_batch: Simulated (and at most as many measured) trajectories of each distribution-matching fit; its
            memory stays bounded at any size (the gradient is taken a chunk of trajectories at a time).
        families: Prior families tried for the coefficients, simplest first.
        c2st_classifier: The C2ST judge of the gap table ("auto", "mlp" or "conv").
        seed: Seed of every draw of the workflow.
        fit_cache: A folder where each finished coefficient fit is stored and from which a run that asks for the same
            fit reads it (:mod:`otgb.discovery.fit_cache`): a stopped run started again with the same folder resumes.
            ``auto``: ``fit_cache`` beside the run directories (``runs/<config stem>/fit_cache``) under ``otgb discover``,
            none where the workflow is called directly; ``null``: no fit is stored.
    """

    def __init__(
        self,
        n_permutations: int = 999,
        alpha: float = 0.05,
        regions_per_axis: int = 4,
        locate_rows: int = 1000,
        score_rows: int = 2000,
        n_trajectories: int = 256,
        n_bootstrap: int = 30,
        theta_products: bool = False,
        position_degree: int = 0,
        strong_candidates: int = 3,
        fit_steps: int = 50,
        fit_batch: int = 1024,
        families: tuple[str, ...] = FAMILIES,
        c2st_classifier: str = "auto",
        seed: int = 0,
        fit_cache: str | None = "auto",
    ) -> None:
        if n_permutations < 19 or not 0 < alpha < 1 or regions_per_axis < 1 or min(locate_rows, score_rows) < 10:
            raise InputError(
                f"discover: need n_permutations >= 19, 0 < alpha < 1, regions_per_axis >= 1, locate_rows >= 10, "
                f"score_rows >= 10; got {n_permutations}, {alpha}, {regions_per_axis}, {locate_rows}, {score_rows}"
            )
        if n_trajectories < 10 or n_bootstrap < 1 or fit_steps < 1 or fit_batch < 2 or strong_candidates < 0:
            raise InputError(
                "discover: need n_trajectories >= 10, n_bootstrap >= 1, fit_steps >= 1, fit_batch >= 2, strong_candidates >= 0"
            )
        if isinstance(position_degree, bool) or not (isinstance(position_degree, int) and 0 <= position_degree <= MAX_DEGREE):
            raise InputError(f"discover.position_degree={position_degree!r} is invalid; expected a whole number 0..{MAX_DEGREE}")
        unknown = [f for f in families if f not in FAMILIES]
        if unknown or not families:
            raise InputError(f"discover.families={list(families)}: expected a non-empty list among {list(FAMILIES)}")
        self.n_permutations, self.alpha, self.regions_per_axis = n_permutations, alpha, regions_per_axis
        self.locate_rows, self.score_rows = locate_rows, score_rows
        self.n_trajectories, self.n_bootstrap, self.theta_products = n_trajectories, n_bootstrap, theta_products
        self.position_degree = position_degree
        self.strong_candidates, self.fit_steps, self.fit_batch = strong_candidates, fit_steps, fit_batch
        self.families, self.c2st_classifier, self.seed = tuple(families), c2st_classifier, seed
        self.fit_cache = fit_cache
        self.cache = None if fit_cache in (None, "auto") else FitCache(fit_cache)  # refuses a file before any work
        self.device = torch.device("cpu")  # of the coefficient fits: otgb discover's is the trainer's

    def cache_beside(self, runs: Path) -> None:
        """Resolve ``fit_cache: auto`` to the folder ``runs/fit_cache`` (``runs``: where the run directories are)."""
        if self.fit_cache == "auto":
            self.cache = FitCache(runs / "fit_cache")


@dataclass
class Measurements:
    """The measured trajectories (n, T, *obs) of each part of the split, the training and test parts' x0 and theta
    where the measurements recorded both, and the sd of their noise (0: noise-free or not given)."""

    train: Tensor
    val: Tensor
    test: Tensor
    train_inputs: tuple[Tensor, Tensor] | None = None
    test_inputs: tuple[Tensor, Tensor] | None = None
    noise: float = 0.0

    @classmethod
    def from_datamodule(cls, datamodule: Any) -> Measurements:
        datamodule.setup("fit")
        datamodule.setup("test")
        val, test = datamodule.val_set["y"].flatten(0, 1), datamodule.test_set["y"].flatten(0, 1)
        train_inputs = datamodule.source.training_inputs()
        test_inputs = None if train_inputs is None else (datamodule.test_set["x0"], datamodule.test_set["theta"])
        return cls(datamodule.measured, val, test, train_inputs, test_inputs, datamodule.measurement_noise)

    def pairable(self) -> bool:
        """Whether the paired check (:mod:`otgb.discovery.paired`) applies: inputs recorded and the noise given."""
        return self.train_inputs is not None and self.noise > 0


@dataclass
class Discovery:
    """Everything the report shows."""

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

    @property
    def found(self) -> bool:
        return self.fitted is not None and len(self.fitted.candidates) > 0


# --- simulation helpers ---------------------------------------------------------------
@torch.no_grad()
def simulate_from_priors(physics: PhysicsModel, n: int, seed: int, name: str) -> Tensor:
    """n observed trajectories of ``physics`` with inputs from its priors, (n, T, *obs)."""
    g = generator_for(seed, "discover", name)
    x0, theta = physics.sample_initial_state(n, g), physics.sample_theta(n, g)
    return simulate_in_chunks(physics, x0, theta)


@torch.no_grad()
def simulate_candidate(model: Augmented, n: int, seed: int, name: str) -> Tensor:
    """:func:`simulate_from_priors` for a candidate model: the trajectories that diverge are dropped and logged."""
    g = generator_for(seed, "discover", name)
    x0, theta = model.sample_initial_state(n, g), model.sample_theta(n, g)
    kept, bad = zip(*(_simulate_finite_rows(model, i, x0[i : i + CHUNK], theta[i : i + CHUNK]) for i in range(0, n, CHUNK)))
    bad = torch.cat(bad)
    if bool(bad.any()):
        first, coefficients = theta[int(bad.nonzero()[0])].tolist(), [repr(t.priors["coefficient"]) for t in model.added]
        diverged(name, term_names(model.added), int(bad.sum()), n, first, coefficients)
    return torch.cat(kept)


def _simulate_finite_rows(model: Augmented, first: int, x0: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    with model.rows_from(first):
        return simulate_finite(model, x0, theta)


GREYBOX = "greybox"  # the grey-box's stream of inputs; f_p simulated from it gets the same (x0, theta)


@torch.no_grad()
def greybox_draws(module: Any, n: int, seed: int) -> dict[str, Tensor]:
    """The grey-box's states, f_p and f_phi (in state space) along n generated trajectories from the priors."""
    physics = module.physics
    g = generator_for(seed, "discover", GREYBOX)
    x0, theta = physics.sample_initial_state(n, g), physics.sample_theta(n, g)
    transport_map, device = module.evaluation_map(), module.device
    rng = module.generator.get_state()
    parts = []
    for i in range(0, n, CHUNK):
        z = module.sample_z(len(x0[i : i + CHUNK]))
        parts.append(transport_map.components(x0[i : i + CHUNK].to(device), theta[i : i + CHUNK].to(device), z))
    module.generator.set_state(rng)
    out = {key: torch.cat([p[key] for p in parts]).cpu() for key in parts[0]}
    flat = out["correction"].flatten(0, 1)
    out["correction"] = physics.add_correction(torch.zeros_like(out["states"].flatten(0, 1)), flat).reshape(out["states"].shape)
    out["observed"] = physics.observe(out["states"])
    out["theta"] = theta
    return out


def acting_components(physics: PhysicsModel) -> list[str]:
    """The state components the grey-box's correction can change."""
    probe = torch.zeros(1, *physics.state_shape)
    reach = physics.add_correction(probe, torch.ones(1, *physics.correction_shape)).reshape(len(physics.state_names), -1)
    reach = reach.abs().sum(-1)
    return [name for name, r in zip(physics.state_names, reach) if r > 0]


# --- the steps ----------------------------------------------------------------------
def locate_step(
    physics: PhysicsModel, measured: Tensor, settings: DiscoverySettings, model_name: str = "f_p",
    paired: PairedCheck | None = None,
) -> DisagreementMap:  # fmt: skip
    """The disagreement map between ``measured`` (at most ``settings.locate_rows`` of them, drawn at random) and as many
    trajectories of ``physics`` (f_p, or a candidate model whose diverged trajectories are dropped), with f_p's
    ``paired`` check on the measurements' inputs, if any."""
    tested = at_most(measured, settings.locate_rows, settings.seed)
    simulate = simulate_candidate if isinstance(physics, Augmented) else simulate_from_priors
    simulated = simulate(physics, len(tested), settings.seed, model_name)
    result = locate(
        tested, simulated, physics.observation_times(), physics.observed,
        settings.n_permutations, settings.alpha, settings.regions_per_axis, settings.seed, paired,
    )  # fmt: skip
    result.drawn_from = len(measured) if len(tested) < len(measured) else 0
    return result


def name_step(module: Any, settings: DiscoverySettings) -> tuple[list[Selection], dict, dict[str, Tensor], float]:
    """Regress f_phi on the library, per component; also returns the designs, the draws and |f_phi| / |f_p| (RMS)."""
    physics = module.physics
    draws = greybox_draws(module, settings.n_trajectories, settings.seed)
    selections, designs = [], {}
    for component in acting_components(physics):
        index = physics.state_names.index(component)
        candidates = build_library(physics, [component], settings.theta_products, settings.position_degree)
        design = design_matrix(
            physics, candidates, draws["states"], draws["theta"], draws["correction"][:, :, index], settings.seed
        )
        selections.append(regress(design, component, settings.n_bootstrap, settings.seed))
        designs[component] = design
    share = float(draws["correction"].pow(2).mean().sqrt() / draws["physics"].pow(2).mean().sqrt().clamp_min(1e-12))
    return selections, designs, draws, share


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


def cross_check_step(strong: list[tuple], fitting: Fitting) -> list[dict]:
    """Each strong candidate alone added to f_p, its coefficient fitted: the share of f_p's held-out gap it closes,
    and how far below f_p alone's its held-out energy lies, with that difference's standard error."""
    baseline = discrepancies(fitting.physics, [], [], fitting.val, fitting.seed)
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


def fitting_for(physics: PhysicsModel, data: Measurements, settings: DiscoverySettings, designs: dict) -> Fitting:
    """The run's :class:`otgb.discovery.refine.Fitting`: the settings' steps, batch and seed, and each library
    candidate's natural scale, the slope at which its term alone would be as large as f_phi on its component."""
    natural = {c: _natural_scale(c, design) for design in designs.values() for c in design.candidates}
    train, val = (at_most(part, settings.score_rows, settings.seed) for part in (data.train, data.val))
    steps = (settings.fit_steps, settings.fit_batch, settings.seed)
    return Fitting(physics, train, val, *steps, natural, settings.cache, settings.device)


def at_most(rows: Tensor, n: int, seed: int) -> Tensor:
    """``rows``, or ``n`` of them drawn at random (in their order) where there are more. One permutation per number of
    rows, whatever the model compared with them: the before and after maps of a part see the same trajectories, and a
    smaller subset of a part is a part of a larger one."""
    if len(rows) <= n:
        return rows
    drawn = torch.randperm(len(rows), generator=generator_for(seed, "discover", "rows", len(rows)))
    return rows[drawn[:n].sort().values]


def _natural_scale(candidate: Candidate, design: Any) -> float:
    index = design.candidates.index(candidate)
    return float(np.sqrt((design.y**2).mean()) / max(design.scale[index], 1e-12))


MAX_FORWARD_TERMS = 6  # models on f_phi's route at most (its prune refits O(k^2) models)


def _on(candidate: Candidate) -> str:
    return f"{candidate.feature} on d{candidate.component}/dt"


def add_step(selections: list[Selection], designs: dict, fitting: Fitting):
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
    the terms left out are reported as dropped. Returns the kept terms' constant fit, the dropped
    terms, and whether the route was truncated.
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
    return current, dropped, truncated


def evidence_step(
    kept: FittedTerms, result: Discovery, designs: dict, fitting: Fitting, per_term: int
) -> tuple[FittedTerms, list[Comparison], list[dict]]:  # fmt: skip
    """The kept terms against every single-term swap among ``result``'s strong candidates, the terms each moves with in
    its regression and Coulomb friction, on the validation measurements (:mod:`otgb.discovery.evidence`); a swap that
    fits better by two standard errors is taken, and an added strong candidate that does so with a coefficient whose
    95 % interval excludes zero. Returns the kept fit, its comparisons and the additions."""

    def start(candidate: Candidate) -> float:
        return _initial([candidate], designs)[0]

    def interval(fitted: FittedTerms) -> tuple[float, float] | None:
        intervals = fitted_intervals(fitting, fitted)
        return None if intervals is None else intervals.centre[-1]

    partners = moves_with(result.selections)
    kept, comparisons, added = weigh(fitting.physics, kept, result.cross_check, per_term, fitting, start, interval, partners)
    for c in comparisons:
        margin = f"{c.standard_errors:+.1f} standard errors" if math.isfinite(c.difference) else "the swapped model diverges"
        progress(f"evidence: {c.replaced.feature} against {c.by.feature}: {margin}")
    return kept, comparisons, added


def choose_prior(constant: FittedTerms, fitting: Fitting, families: tuple[str, ...]) -> FamilyChoice:
    """Each prior family of ``families`` for the constant fit's terms, fitted from its optimum; the choice on the
    training measurements (:mod:`otgb.discovery.variation`)."""
    start = [p.value for p in constant.priors]

    def refit(family: str) -> FittedTerms:
        return fitting(constant.candidates, start, family, natural_scales=False)

    return choose_family_of(fitting.physics, constant, fitting.train, families, refit, fitting.seed)


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


def family_step(kept: FittedTerms, fitting: Fitting, families: tuple[str, ...]) -> tuple[FamilyChoice, list[dict]]:
    """The prior family of ``kept``'s terms (:func:`choose_prior`); when it varies, the terms are pruned again in it.

    Every earlier step fits constant coefficients. When the effect varies between trajectories, a
    constant one misfits the measurements, and a further term can lower the held-out discrepancy by
    taking up part of the variation (on the one-to-many pendulum, whose friction is one of two values,
    Coulomb friction was added beside viscous friction). Fitted with the chosen family, such a term is
    no longer needed: it is dropped (:func:`prune`) and the family is chosen again for the terms left.
    Returns the choice and the dropped terms.
    """
    choice = choose_prior(kept, fitting, families)
    if choice.fitted.family == "constant" or len(kept.candidates) == 1:
        return choice, []
    pruned = prune(choice.fitted, fitting)
    if len(pruned.candidates) == len(kept.candidates):
        return choice, []
    dropped = [{"feature": c.feature, "component": c.component} for c in kept.candidates if c not in pruned.candidates]
    constant = fitting(pruned.candidates, [centre(p) for p in pruned.priors], natural_scales=False)
    return choose_prior(constant, fitting, families), dropped


def final_regression(selections: list[Selection], designs: dict, kept: list[Candidate], settings: DiscoverySettings) -> list:
    """The regression of f_phi on the kept terms alone, per component (intervals, shares, ambiguity)."""
    terms = []
    for selection in selections:
        mine = [c for c in kept if c.component == selection.component]
        if mine:
            inclusion = {Candidate(f, selection.component): p for f, p in selection.inclusion.items()}
            terms += describe_terms(designs[selection.component], mine, inclusion, settings.n_bootstrap, settings.seed)
    return terms


def _initial(candidates: list[Candidate], designs: dict) -> list[float]:
    """Least-squares starting values per component for ``candidates``."""
    values = {}
    for component in dict.fromkeys(c.component for c in candidates):
        mine = [c for c in candidates if c.component == component]
        values.update(zip(mine, subset_coefficients(designs[component], mine)))
    return [values[c] for c in candidates]


def gap_step(sources: dict[str, Tensor], test: Tensor, settings: DiscoverySettings) -> dict[str, dict[str, float]]:
    """MMD, C2ST and energy distance of each source's draws against the test measurements, and the Reference."""
    gap = {name: scores(draws, test, settings) for name, draws in sources.items()}
    g = torch.Generator().manual_seed(settings.seed)
    order = torch.randperm(len(test), generator=g)
    half = len(test) // 2
    gap["reference"] = scores(test[order[:half]], test[order[half : 2 * half]], settings)
    return gap


def scores(p: Tensor, q: Tensor, settings: DiscoverySettings) -> dict[str, float]:
    shape = tuple(p.shape[1:])
    p, q = p.flatten(1).double(), q.flatten(1).double()
    judge = c2st(p.float(), q.float(), folds=5, seed=settings.seed, classifier=settings.c2st_classifier, trajectory_shape=shape)
    return {
        "mmd": float(mmd_multiscale(p, q)),
        "c2st": float(judge["c2st"]),
        "c2st_std": float(judge["c2st_std"]),
        "energy": float(energy_distance(p, q)),
    }


def run(module: Any, data: Measurements, settings: DiscoverySettings, before: DisagreementMap) -> Discovery:
    """Steps 3-5 on a trained grey-box ``module`` (a MapTraining), after a significant locate; a candidate model
    whose solve diverges is dropped where it diverged and listed in ``diverged``."""
    with DivergenceLog() as log:
        result = _run(module, data, settings, before)
    result.diverged = log.records
    return result


def _run(module: Any, data: Measurements, settings: DiscoverySettings, before: DisagreementMap) -> Discovery:
    physics = module.physics
    result = Discovery(before, describe(before))
    result.selections, designs, draws, result.correction_share = name_step(module, settings)
    selected = [(t.candidate, t.coefficient) for s in result.selections for t in s.terms]
    proposed = [f"{c.feature} on d{c.component}/dt: {v:.4g}" for c, v in selected]
    progress(
        f"f_phi's regression proposes {proposed}; each is checked against the measurements next"
        if proposed
        else "f_phi's regression proposes no term"
    )
    strong = strong_candidates(result.selections, designs, settings.strong_candidates)
    fitting = fitting_for(physics, data, settings, designs)
    result.cross_check = cross_check_step(strong, fitting)
    progress(f"cross-checked {len(strong)} candidates alone")
    result.undertrained = undertrained(module, fitting.val, settings)
    kept, truncated = None, False
    if selected and result.undertrained is None:
        kept, result.dropped, truncated = add_step(result.selections, designs, fitting)
        progress(f"kept {[c.feature for c in kept.candidates]}, coefficients {short(kept.priors)}")
    unused = bool(selected) and result.undertrained is not None
    result.search_reason = search_reason(physics, kept, truncated, fitting.val, settings, unused)
    if result.search_reason is not None:
        kept = search_step(kept, result, designs, fitting)
    if kept is not None:
        kept, result.evidence, result.added = evidence_step(kept, result, designs, fitting, settings.strong_candidates)
        result.family, dropped = family_step(kept, fitting, settings.families)
        result.dropped += dropped
        result.fitted = result.family.fitted
        progress(f"fitted {result.fitted.family} coefficients {short(result.fitted.priors)}")
    sources = {
        "f_p": simulate_from_priors(physics, len(data.test), settings.seed, "gap-f_p"),
        "greybox": generated(module, len(data.test), settings.seed),
    }
    if result.found:
        result.final_terms = final_regression(result.selections, designs, result.fitted.candidates, settings)
        result.intervals = fitted_intervals(fitting, result.fitted)
        progress(f"intervals: {rounded(result.intervals.centre) if result.intervals else 'none (the fit is not at a minimum)'}")
        sources["augmented"] = simulate_candidate(result.fitted.model(physics), len(data.test), settings.seed, "gap-augmented")
        result.before_on_test = locate_step(physics, data.test, settings, "f_p-test")
        result.after = locate_step(result.fitted.model(physics), data.test, settings, "augmented")
        result.paired_after = paired_after(result.fitted, physics, data, settings.alpha)
    progress("verifying on the test part")
    result.gap, result.draws = gap_step(sources, data.test, settings), sources
    if result.found:
        result.closer = closer_step(result.fitted.model(physics), physics, data.test, settings)
        result.sentence_after = sentence_after(result)
    return result


def sentence_after(result: Discovery) -> str:
    """The sentence on the augmented physics against the test part: its disagreement map; where the map sees no
    difference but the gap table's C2ST does, that; the same map of f_p alone (:func:`beside_f_p`); the paired check."""
    sentence = describe(result.after, b_name="augmented-physics") + " (on the test part, which no fit saw)"
    if not result.after.any_significant and (told := c2st_tells_apart(result.gap, "augmented")):
        sentence += (
            f"; but the gap table's C2ST tells the augmented physics from the measurements ({told}): a difference "
            "remains that the map does not see"
        )
    sentence += beside_f_p(result.before_on_test)
    return sentence + (f"; {result.paired_after.sentence()}" if result.paired_after is not None else "")


def c2st_tells_apart(gap: dict[str, dict[str, float]], source: str) -> str | None:
    """Where the gap table's C2ST tells ``source``'s draws from the test measurements, its accuracy above 0.5 by more
    than two of the Reference's standard deviations (half the test measurements against the other half, repeated),
    the numbers that say so; else None (also where either figure is missing or not finite)."""
    judged, reference = gap.get(source, {}), gap.get("reference", {})
    if "c2st" not in judged or "c2st_std" not in reference or not judged["c2st"] - 0.5 > 2 * reference["c2st_std"]:
        return None
    return f"C2ST {judged['c2st']:.2f}, the Reference's {reference['c2st']:.2f} +- {reference['c2st_std']:.2f}"


CLOSER_DRAWS = 4  # trajectories of each model per test trajectory in the test of which is nearer: more draws, more power


def closer_step(model: Augmented, physics: PhysicsModel, test: Tensor, settings: DiscoverySettings) -> Closeness | None:
    """Whether the augmented physics ``model`` is nearer to the test measurements (at most ``locate_rows`` of them,
    drawn at random) than f_p alone (:mod:`.closer`), on fresh draws of both: ``CLOSER_DRAWS`` per test trajectory, at
    most ``locate_rows`` and at least as many as the test trajectories. None where too few trajectories of either
    model stay finite to test (the augmented physics's divergences are logged and counted against it)."""
    tested = at_most(test, settings.locate_rows, settings.seed)
    n = max(len(tested), min(CLOSER_DRAWS * len(tested), settings.locate_rows))
    augmented = simulate_candidate(model, n, settings.seed, "closer-augmented")
    f_p = simulate_from_priors(physics, n, settings.seed, "closer-f_p")
    try:
        return closer(augmented, f_p, tested, settings.n_permutations, settings.alpha, settings.seed, n - len(augmented))
    except ValueError:  # too few finite trajectories: the verdict says no test could run
        return None


def beside_f_p(before_on_test: DisagreementMap) -> str:
    """The same tests of f_p alone on the same test part, for the sentence on the augmented physics: an agreement
    after the fix means something only where f_p alone disagrees with these trajectories."""
    if not before_on_test.any_significant:
        return "; nor between f_p alone and them, so this agreement alone does not show what the fix changed"
    cells = int(before_on_test.significant.sum())
    if cells:
        where = f"in {cells} of {before_on_test.significant.numel()} cells"
    else:
        where = "as whole trajectories" if before_on_test.whole_significant else "on their recorded inputs"
    return f"; f_p alone, tested the same way, differs from them {where}"


def paired_after(fitted: FittedTerms, physics: PhysicsModel, data: Measurements, alpha: float) -> PairedCheck | None:
    """The named terms' paired check on the test part at level ``alpha``, where it applies: recorded inputs, a given
    noise and constant coefficients (with a spread, a coefficient per trajectory is unknown and nothing pairs)."""
    if not data.pairable() or fitted.family != "constant":
        return None
    model, (x0, theta) = fitted.model(physics), data.test_inputs
    coefficients = model.sample_theta(len(theta), torch.Generator())[:, theta.shape[1] :]  # constants: the same each row
    names = {"model": "the augmented physics", "part": "the test part's"}
    check = paired_check(model, data.test, x0, torch.cat([theta, coefficients], dim=1), data.noise, **names)
    check.significant = check.pvalue < alpha
    return check


def search_reason(
    physics: PhysicsModel, kept: FittedTerms | None, truncated: bool, val: Tensor, settings: DiscoverySettings, unused: bool
) -> str | None:
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
    if settings.position_degree and getattr(physics, "coordinate_names", ()):
        return (
            "terms fixed in space were asked for (discover.position_degree), so they are searched for directly, "
            "not only along f_phi's route"
        )
    if locate_step(kept.model(physics), val, settings, "augmented-check").any_significant:
        return "the physics augmented along f_phi's route still disagrees with the validation measurements"
    return None


def search_step(kept: FittedTerms | None, result: Discovery, designs: dict, fitting: Fitting) -> FittedTerms | None:
    """The library search (:mod:`otgb.discovery.search`) for ``result.search_reason``; its model replaces ``kept`` as
    :func:`replaces` says. Returns the constant fit kept."""
    progress(f"{result.search_reason}: searching the local library")
    candidates = [c for design in designs.values() for c in design.candidates]
    current = {} if kept is None else {c: p.value for c, p in zip(kept.candidates, kept.priors)}
    init = [current.get(c, 0.0) for c in candidates]
    found, result.search, result.unsupported = search(candidates, init, fitting, progress)
    if found is None or (kept is not None and not replaces(found, kept)):
        progress("search: nothing better than " + ("f_phi's terms" if kept else "f_p alone"))
        return kept
    result.dropped, result.route = [], "library search"
    progress(f"search: kept {[c.feature for c in found.candidates]}, coefficients {short(found.priors)}")
    return found


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


def undertrained(module: Any, heldout: Tensor, settings: DiscoverySettings) -> dict[str, float] | None:
    """The grey-box's and f_p's held-out discrepancy when the grey-box does not beat f_p by two standard errors
    (:func:`otgb.discovery.refine.beats`): its correction is then no evidence, and the naming relies on the
    library search. None when the grey-box is better.

    Both are simulated from the same inputs (x0, theta) in each draw (common random numbers), so their scores differ
    by the correction, not by the luck of the draws; what the few validation trajectories leave uncertain remains.
    """
    physics = module.physics
    n, m, seed = len(heldout), max(len(heldout), UNDERTRAINED_DRAWS), settings.seed
    greybox = sample_scores(lambda r: generated(module, m, seed + 100 + r), heldout, UNDERTRAINED_REPEATS)
    alone = sample_scores(lambda r: simulate_from_priors(physics, m, seed + 100 + r, GREYBOX), heldout, UNDERTRAINED_REPEATS)
    if beats(greybox, alone):
        return None
    gain, error = difference(greybox, alone)
    progress(f"the OT grey-box {undertrained_text(gain, error, n, greybox.mean, alone.mean)}")
    return {
        "greybox_heldout_energy": greybox.mean, "f_p_heldout_energy": alone.mean,
        "difference": gain, "standard_error": error, "validation_trajectories": n,
    }  # fmt: skip


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


@torch.no_grad()
def generated(module: Any, n: int, seed: int) -> Tensor:
    """n trajectories of the grey-box with inputs from the priors, (n, T, *obs)."""
    return greybox_draws(module, n, seed)["observed"][:, -module.physics.n_obs :]


def term_name(candidate: Candidate, coefficient: float, physics: PhysicsModel) -> str:
    return physical_name(candidate.feature, candidate.component, coefficient, physics)
