"""Parametric forms in discovery: where linear terms leave doubt, a form nonlinear in its parameters is weighed.

A friction that saturates with speed is fitted by the linear library as viscous friction, Coulomb friction or
both, ambiguous with each other, and the answer never gives the form. So, after the evidence step, the kept
model K (constant coefficients) is weighed against K_F for each form F (:mod:`otgb.physics.forms`) that
applies: the friction forms (saturating, rational, Stribeck, power law) on a velocity whose own friction terms
K holds, a Gaussian bump on a field whose terms fixed in space K holds, and every form a user declares
(``discover.forms``: its class path, component, variables and parameters' ranges). K_F is K with the terms F
covers replaced by ``c * shape(variables; parameters)`` (a declared form covers every kept term on its
component). The built-in forms are tried where the linear terms leave doubt: a covered term ambiguous with an
alternative, two covered terms on one component, or a remainder (K still disagrees with the validation part).

For each K_F:

1. **Start**: f_phi on the component along the grey-box's trajectories (the regression's design), less the
   kept terms F does not cover, is fitted by ``c * shape`` on a grid of the parameters in their ranges (c by
   least squares at each point); the best point is the start.
2. **Fit**: every coefficient of K_F, c and the form's parameters (the positive ones on a log scale) by
   distribution matching on the training part (:func:`otgb.discovery.lbfgs.minimise`), inputs fixed as in
   every fit.
3. **Score** on the validation part with the common random numbers of every model
   (:func:`otgb.discovery.scores.discrepancies`), the form written in with its fitted parameters
   (``rational(velocity;v0=0.8)``, a feature like any other).
4. **Intervals**: the sandwich of the fit (:func:`otgb.discovery.intervals.sandwich`) over all of K_F's
   parameters at once, so c's and each form parameter's 95 % intervals account for each other.

K_F replaces K where it fits the validation part better by two standard errors, or, having no more parameters
than the terms it replaces (a saturating friction's c and v0 for viscous plus Coulomb friction), fits it better at
all: of two models as sparse that the data cannot tell apart, the nearer, as in the library search
(:func:`otgb.discovery.workflow.replaces`), and the verdict then says that the validation part cannot tell the two
apart. Its parameters must also lie inside their ranges (a saturation speed at the top of its range is a linear
friction), each with an interval, none of which holds a value at which the form is a library term (a power law's
p = 1 or 2). Of several such forms, the best fit is taken; those it cannot be told from are listed.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from otgb.discovery.chunked import Simulate
from otgb.discovery.crossfit import cross_fitted, refit_steps
from otgb.discovery.discrepancy import Target
from otgb.discovery.evidence import Comparison
from otgb.discovery.families import CONSTANT
from otgb.discovery.intervals import STEP, Z95, sandwich
from otgb.discovery.lbfgs import minimise
from otgb.discovery.library import Candidate, fixed_in_space, signed_kind, term_name
from otgb.discovery.log import progress
from otgb.discovery.refine import FitSample, FittedTerms, Fitting
from otgb.discovery.scores import Scores, beats, clears, difference, discrepancies
from otgb.physics.augmented import Augmented
from otgb.physics.forms import FRICTION_FORMS, Range, form_feature, form_named
from otgb.physics.priors import Constant, Prior
from otgb.physics.terms import FormTerm, LibraryTerm

GRID_POINTS = 400  # points of the start's grid over a form's parameters, at most


@dataclass(frozen=True)
class Offer:
    """A form to weigh: its name (or class path), the component it adds to, its variables, where its parameters
    are looked for, and the kept terms it replaces."""

    form: str
    component: str
    variables: tuple[str, ...]
    ranges: dict[str, Range]
    covers: tuple[Candidate, ...]


@dataclass(frozen=True)
class FormFit:
    """One form fitted in place of the terms it covers: its parameters' values and 95 % intervals (None: the fit is
    not at a minimum), its coefficient's interval, the model with the form written in (constant coefficients, scored
    on the validation part), how much better than the kept model it fits there (> 0: better) and why it is not
    taken (None: it qualifies)."""

    offer: Offer
    values: dict[str, float]
    intervals: dict[str, Range] | None
    coefficient_interval: Range | None
    fitted: FittedTerms
    difference: float
    standard_error: float
    refused: str | None

    @property
    def candidate(self) -> Candidate:
        return self.fitted.candidates[-1]

    def to_dict(self) -> dict:
        return {
            "form": self.offer.form, "component": self.offer.component, "variables": list(self.offer.variables),
            "feature": self.candidate.feature, "replaces": [c.feature for c in self.offer.covers],
            "coefficient": self.fitted.priors[-1].value,
            "coefficient_interval": list(self.coefficient_interval) if self.coefficient_interval else None,
            "parameters": parameter_records(self), "difference": self.difference,
            "standard_error": self.standard_error, "refused": self.refused,
        }  # fmt: skip


def parameter_records(fit: FormFit) -> list[dict]:
    """Each nonlinear parameter's name, value, 95 % interval (or None) and range."""
    return [
        {"name": k, "value": v, "interval": list(fit.intervals[k]) if fit.intervals else None, "range": list(fit.offer.ranges[k])}
        for k, v in fit.values.items()
    ]  # fmt: skip


@dataclass(frozen=True)
class FormStep:
    """The kept model after the forms were weighed (the adopted form's model, or the kept one), why they were
    weighed (None: not), each form's fit and the one adopted."""

    kept: FittedTerms
    reason: str | None = None
    tried: list[FormFit] = field(default_factory=list)
    adopted: FormFit | None = None
    alike_fits: list[FormFit] = field(default_factory=list)  # the other qualified forms it cannot be told from
    replaced_from: FittedTerms | None = None  # the kept linear model the adopted form replaced terms of

    def said(self, physics) -> list[str]:
        """The verdict's part on the adopted form: what it replaces, by how many standard errors, what it cannot be told
        from; none where no form was adopted."""
        fit = self.adopted
        if fit is None:
            return []
        errors = fit.difference / fit.standard_error if fit.standard_error > 0 else math.inf
        covered = " and ".join(term_name(c, v.value, physics) for c, v in zip(fit.offer.covers, self.replaced_values))
        label = term_name(fit.candidate, fit.fitted.priors[-1].value, physics)
        text = f"{label} replaces {covered or 'no linear term'}"
        if clears(fit.difference, fit.standard_error):
            text += f": it fits the validation part better by {errors:.1f} standard errors"
        else:
            text += (
                f": the validation part cannot tell the two apart by two standard errors ({errors:+.1f}); of two models "
                "with as many parameters, the nearer is kept"
            )
        alike = [term_name(f.candidate, f.fitted.priors[-1].value, physics) for f in self.alike_fits]
        return [text + (f"; nor can it tell it from {' or '.join(alike)}" if alike else "")]

    @property
    def replaced_values(self) -> list:
        """The kept model's priors of the terms the adopted form replaced."""
        return [p for c, p in zip(self.replaced_from.candidates, self.replaced_from.priors) if c in self.adopted.offer.covers]


def offers(physics, kept: FittedTerms, designs: dict, declared: list[dict]) -> list[Offer]:
    """The forms to weigh against ``kept``: the built-in ones that apply, then the declared ones."""
    found = []
    for component in dict.fromkeys(c.component for c in kept.candidates):
        design = designs.get(component)
        frictions = tuple(
            c for c in kept.candidates if c.component == component and signed_kind(c.feature, component, physics) == "friction"
        )
        if frictions and design is not None:
            found += [_built_in(name, component, (component,), frictions, design) for name in FRICTION_FORMS]
        fixed = tuple(c for c in kept.candidates if c.component == component and fixed_in_space(c.feature, physics))
        coordinates = tuple(getattr(physics, "coordinate_names", ()))
        if fixed and design is not None and len(coordinates) in (1, 2):
            found.append(_built_in("bump" if len(coordinates) == 1 else "bump2", component, coordinates, fixed, design))
    for entry in declared:
        covers = tuple(c for c in kept.candidates if c.component == entry["component"])
        found.append(Offer(entry["class_path"], entry["component"], tuple(entry["variables"]), dict(entry["ranges"]), covers))
    return [offer for offer in found if offer is not None]


def _built_in(name: str, component: str, variables: tuple[str, ...], covers: tuple, design) -> Offer | None:
    """A built-in form's offer, its ranges from its variables' sizes along the grey-box's trajectories (None where the
    design lacks a variable: a coordinate the library did not offer)."""
    columns = [_column(design, v) for v in variables]
    if any(c is None for c in columns):
        return None
    sizes = [float(np.abs(c).max()) for c in columns]
    spans = [(float(c.min()), float(c.max())) for c in columns]
    return Offer(name, component, variables, form_named(name).ranges(sizes, spans), covers)


def _column(design, variable: str) -> np.ndarray | None:
    index = next((i for i, c in enumerate(design.candidates) if c.feature == variable), None)
    return None if index is None else design.X[:, index]


def reason_to_weigh(physics, kept: FittedTerms, comparisons: list[Comparison], built_in: list[Offer], declared: bool,
                    remainder: Callable[[], bool]) -> str | None:  # fmt: skip
    """Why the forms are weighed, or None: declared forms; a covered term ambiguous with an alternative; two covered
    terms on one component; a remainder (checked last: it simulates)."""
    if declared:
        return "forms were declared (discover.forms)"
    covered = {c for offer in built_in for c in offer.covers}
    ambiguous = sorted({c.replaced.feature for c in comparisons if c.ambiguous and c.replaced in covered})
    if ambiguous:
        return f"the measurements cannot tell {', '.join(ambiguous)} from an alternative"
    if any(len(offer.covers) > 1 for offer in built_in):
        return "two linear terms share one effect"
    if built_in and remainder():
        return "the linear terms leave a remainder (the augmented physics still disagrees with the validation part)"
    return None


def form_step(kept: FittedTerms, comparisons: list[Comparison], designs: dict, fitting: Fitting, declared: list[dict],
              remainder: Callable[[], bool]) -> FormStep:  # fmt: skip
    """Weigh the forms that apply against ``kept`` (module docstring)."""
    offered = offers(fitting.physics, kept, designs, declared)
    built_in = [o for o in offered if o.form in FRICTION_FORMS or o.form.startswith("bump")]
    reason = reason_to_weigh(fitting.physics, kept, comparisons, built_in, bool(declared), remainder) if offered else None
    if reason is None:
        return FormStep(kept)
    progress(f"forms: {reason}; weighing {[o.form for o in offered]}")
    tried = [fit_form(offer, kept, designs, fitting) for offer in offered]
    for fit in tried:
        values = ", ".join(f"{k}={v:.4g}" for k, v in fit.values.items())
        said = f"{fit.difference / fit.standard_error if fit.standard_error > 0 else 0:+.1f} standard errors"
        progress(
            f"forms: {fit.offer.form} ({values}) against the linear terms: {said}" + (f"; {fit.refused}" if fit.refused else "")
        )
    qualified = [fit for fit in tried if fit.refused is None]
    if not qualified:
        return FormStep(kept, reason, tried)
    adopted = min(qualified, key=lambda fit: fit.fitted.heldout.mean)
    alike = [f for f in qualified if f is not adopted and not beats(adopted.fitted.heldout, f.fitted.heldout)]
    progress(f"forms: {adopted.candidate.feature} replaces {[c.feature for c in adopted.offer.covers]}")
    return FormStep(adopted.fitted, reason, tried, adopted, alike, kept)


def fit_form(offer: Offer, kept: FittedTerms, designs: dict, fitting: Fitting) -> FormFit:
    """:class:`FormFit` of ``offer`` in place of the terms it covers in ``kept`` (module docstring, steps 1-4)."""
    form = form_named(offer.form)
    others = [(c, p.value) for c, p in zip(kept.candidates, kept.priors) if c not in offer.covers]
    amplitude, start = _start(offer, others, designs[offer.component] if offer.component in designs else None)
    problem = _Problem(fitting, offer, [c for c, _ in others], form.parameters, form.positive)
    p0 = torch.tensor([v for _, v in others] + [amplitude] + problem.to_fitted(start), dtype=torch.float64)
    p = problem.fit(p0)
    values = problem.values_of(p)
    candidates, priors = _terms_of(problem, offer, [c for c, _ in others], p)
    heldout = _heldout(fitting, offer, [c for c, _ in others], p, (candidates, priors))
    fitted = FittedTerms(CONSTANT, candidates, priors, heldout, problem.losses, [float(v) for v in p0[: len(priors)]])
    fitting.natural.setdefault(candidates[-1], abs(amplitude) or 1.0)  # its coefficient's size, for the later fits
    gap, error = difference(heldout, kept.heldout)
    refused = _refused_by_fit(form, offer, values, gap, error)
    intervals = problem.intervals(p) if refused is None else None  # the sandwich only for a form still in the running
    named = None if intervals is None else {k: intervals[len(priors) + i] for i, k in enumerate(form.parameters)}
    coefficient = None if intervals is None else intervals[len(priors) - 1]
    refused = refused or _refused_by_intervals(form, named)
    return FormFit(offer, values, named, coefficient, fitted, gap, error, refused)


def _terms_of(problem: _Problem, offer: Offer, others: list[Candidate], p: Tensor) -> tuple[list[Candidate], list[Prior]]:
    """The candidates and constant priors of the form model at ``p``: the other terms, then the form."""
    form = Candidate(form_feature(offer.form, offer.variables, problem.values_of(p)), offer.component)
    return [*others, form], [Constant(float(v)) for v in p[: problem.k]]


def _heldout(
    fitting: Fitting, offer: Offer, others: list[Candidate], p: Tensor, terms: tuple[list[Candidate], list[Prior]]
) -> Scores:
    """The form model's held-out scores: ``terms`` (fitted to ``p``) on the validation part or, with folds, the same fit
    on each fold's complement started at ``p``, :func:`~otgb.discovery.crossfit.refit_steps` iterations, scored on the
    fold (:mod:`otgb.discovery.crossfit`)."""
    physics, seed, device = fitting.physics, fitting.seed, fitting.device
    if fitting.folds is None:
        return discrepancies(physics, *terms, fitting.val, seed, device=device)
    form = form_named(offer.form)

    def score_fold(k: int, rest: Tensor, held_out: Tensor) -> Scores:
        on_rest = replace(fitting, train=rest, steps=refit_steps(fitting.steps))
        problem = _Problem(on_rest, offer, others, form.parameters, form.positive)
        return discrepancies(physics, *_terms_of(problem, offer, others, problem.fit(p)), held_out, seed, device=device)

    return cross_fitted(fitting.folds, score_fold)


def _refused_by_fit(form, offer: Offer, values: dict[str, float], gap: float, error: float) -> str | None:
    """Why a fitted form is not taken, from its parameters' values and its validation score; None if neither bars it."""
    outside = [k for k, v in values.items() if not offer.ranges[k][0] <= v <= offer.ranges[k][1]]
    if outside:
        return f"{', '.join(outside)} left the range it is looked for in"
    as_sparse = len(form.parameters) + 1 <= len(offer.covers)  # no more parameters than the terms it replaces
    if not math.isfinite(gap) or not (clears(gap, error) or (as_sparse and gap > 0)):
        more = "" if as_sparse else " (it has more parameters than the terms it replaces)"
        return f"it does not fit the validation part better by two standard errors{more}"
    return None


def _refused_by_intervals(form, intervals: dict | None) -> str | None:
    """Why a form that fits well enough is not taken, from its parameters' intervals; None if they qualify it."""
    if intervals is None:
        return "its parameters have no interval (the fit is not at a minimum)"
    limits = form.library_values
    held = [f"{k} = {v:g}" for k, (low, high) in intervals.items() for v in limits.get(k, ()) if low <= v <= high]
    return f"its intervals hold {', '.join(held)}, where it is a library term" if held else None


def _start(offer: Offer, others: list, design) -> tuple[float, dict[str, float]]:
    """The coefficient and parameters of ``c * shape`` nearest (least squares) to f_phi less the other kept terms, over
    a grid of the parameters in their ranges; the ranges' middles and a unit coefficient without a design."""
    form = form_named(offer.form)
    axes = [_axis(lo, hi, k in form.positive, _points(len(form.parameters))) for k, (lo, hi) in offer.ranges.items()]
    columns = [_column(design, v) for v in offer.variables] if design is not None else [None]
    if any(c is None for c in columns):
        return 1.0, {k: float(axis[len(axis) // 2]) for k, axis in zip(offer.ranges, axes)}
    beside = [(v, _column(design, c.feature)) for c, v in others]
    target = design.y - sum((v * column for v, column in beside if column is not None), 0.0)
    inputs = [torch.as_tensor(c, dtype=torch.float64) for c in columns]
    best = (math.inf, 1.0, {})
    for point in itertools.product(*axes):
        with np.errstate(all="ignore"):
            h = form.shape(inputs, [torch.tensor(v, dtype=torch.float64) for v in point]).numpy()
        norm = float(h @ h)
        if not (math.isfinite(norm) and norm > 0):
            continue
        c = float(h @ target) / norm
        residual = float(((target - c * h) ** 2).sum())
        if residual < best[0]:
            best = (residual, c, dict(zip(offer.ranges, map(float, point))))
    return best[1], best[2] or {k: float(axis[len(axis) // 2]) for k, axis in zip(offer.ranges, axes)}


def _points(parameters: int) -> int:
    return max(3, int(GRID_POINTS ** (1 / max(parameters, 1))))


def _axis(low: float, high: float, positive: bool, points: int) -> np.ndarray:
    return np.geomspace(low, high, points) if positive and low > 0 else np.linspace(low, high, points)


class _Problem:
    """The fit of one form model: p = (the other coefficients, c, the form's parameters, the positive ones as
    logarithms), the training part's fixed sample, the simulation of theta rows from p."""

    def __init__(self, fitting: Fitting, offer: Offer, others: list[Candidate], names: tuple, positive: tuple) -> None:
        self.fitting, self.names, self.positive, self.k = fitting, names, positive, len(others) + 1
        terms = [LibraryTerm(c.feature, c.component, Constant(0.0)) for c in others]
        form_term = FormTerm(offer.form, offer.component, list(offer.variables), Constant(0.0), {n: Constant(1.0) for n in names})
        self.model = Augmented(fitting.physics, [*terms, form_term])
        self.sample = FitSample.draw(fitting.physics, fitting.train, CONSTANT, 1, fitting.batch, fitting.seed)
        self.losses: list[float] = []

    def to_fitted(self, values: dict[str, float]) -> list[float]:
        return [math.log(abs(values[n])) if n in self.positive else values[n] for n in self.names]

    def natural(self, p: Tensor) -> Tensor:
        """p (..., P) with the log-scaled parameters exponentiated: the model's theta columns."""
        logged = torch.tensor([False] * self.k + [n in self.positive for n in self.names])
        return torch.where(logged, p.exp(), p)

    def values_of(self, p: Tensor) -> dict[str, float]:
        return dict(zip(self.names, self.natural(p)[self.k :].tolist()))

    def simulator(self, rows_of: Callable[[Tensor], Tensor], variants: int = 1) -> Simulate:
        """The trajectories of rows of the grid (``variants`` copies of the sample, one after the other), row r's
        theta columns ``rows_of(r)`` (natural units)."""
        sample, model, n = self.sample, self.model, len(self.sample.x0)

        def simulate(rows: slice) -> Tensor:
            index = torch.arange(variants * n)[rows]
            theta = torch.cat([sample.theta[index % n], rows_of(index).float()], 1)
            signals = sample.signals_of(index % n)
            return model.observe(model.solve(model.vector_field, sample.x0[index % n], theta, signals=signals))

        return simulate

    def fit(self, p0: Tensor) -> Tensor:
        """p after the L-BFGS fit from ``p0``, each coefficient moved in units of its start's size."""
        size = p0[: self.k].abs()
        scale = torch.cat([torch.where(size > 0, size, torch.ones_like(size)), torch.ones(len(p0) - self.k, dtype=p0.dtype)])
        shift = torch.zeros_like(p0, requires_grad=True)
        simulate = self.simulator(lambda index: self.natural(p0 + scale * shift).expand(len(index), -1))
        target, n = Target.of(self.sample.targets), len(self.sample.x0)
        self.losses = minimise([shift], simulate, n, target, 1, self.fitting.steps, lambda: bool(torch.isfinite(shift).all()))
        return (p0 + scale * shift).detach()

    def intervals(self, p: Tensor) -> list[Range] | None:
        """The 95 % interval of each of p's entries in natural units (a log-scaled one's endpoints exponentiated)."""
        n, sizes = len(self.sample.x0), torch.where(p.abs() > 0, p.abs(), torch.ones_like(p))
        sizes[self.k :] = 1.0

        def simulator(variants: Tensor) -> Simulate:
            simulate = self.simulator(lambda index: self.natural(variants[index // n]), len(variants))
            return lambda rows: simulate(rows).double()

        covariance = sandwich(p, STEP * sizes, simulator, self.sample.targets.double(), n)
        if covariance is None or isinstance(covariance, int):
            return None
        error = covariance.diagonal().clamp_min(0).sqrt()
        low, high = self.natural(torch.stack([p - Z95 * error, p + Z95 * error]))
        return list(zip(low.tolist(), high.tolist()))
