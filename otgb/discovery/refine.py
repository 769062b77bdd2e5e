"""Add: fit the named terms' coefficients, and their prior, by matching distributions.

The augmented physics f_p + sum_k c_k feature_k (:class:`otgb.physics.Augmented`) is a
differentiable simulator; its coefficients, or the parameters of their prior, are fitted so
that its trajectories (inputs from f_p's priors) match the measured training trajectories in
the unbiased energy distance (:mod:`otgb.metrics.energy`; no bandwidth to tune, unbiased, so
it is 0 on average at the optimum whatever the batch size), between whole trajectories and
between the values at each time step (:func:`discrepancy`). A prior family per fit:

- ``constant``: c (the effect is the same in every trajectory);
- ``uniform``: U(c - w, c + w); ``normal``: N(c, w^2); ``two_point``: c - w or c + w, equally likely
  (the effect varies between trajectories; two-point: it takes one of two values, as two kinds of a
  part or two operating conditions give).

:mod:`otgb.discovery.variation` decides between them (a richer family only if it lowers the
discrepancy by more than two standard errors, over simulation draws with common random numbers,
:func:`discrepancies`), so whether the effect varies is decided by the data. The families are
compared on the training measurements: the richer families add one width per term to hundreds of
trajectories, too little to fit noise, and the training part is several times larger than the
held-out parts, which a spread that varies over time needs to be seen.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor

from otgb.discovery.chunked import backward_in_chunks, chunk_size
from otgb.discovery.fit_cache import FitCache
from otgb.discovery.library import Candidate
from otgb.discovery.log import diverged, held_divergences, logger, say_again
from otgb.metrics.energy import (
    batched_energy,
    cell_and_whole_row_means,
    cell_and_whole_within_means,
    cross_row_means,
    within_means,
)
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel
from otgb.physics.priors import Choice, Constant, Normal, Prior, Uniform
from otgb.physics.solvers import current_solver
from otgb.physics.terms import LibraryTerm

FAMILIES = ("constant", "uniform", "normal", "two_point")  # simplest first
CPU = torch.device("cpu")
HELDOUT_REPEATS = 10  # simulation draws per held-out score
FAMILY_REPEATS = 20  # simulation draws per score of a prior family on the training measurements
# The loss a fit's L-BFGS sees where the model diverges: finite, so that its strong-Wolfe line search
# backtracks (from an infinite value its cubic interpolation gives NaN, and every parameter becomes NaN).
DIVERGED_LOSS = 1e10
MIN_WIDTH = 1e-6  # a prior's smallest width, in units of its coefficient's scale


@dataclass
class Scores:
    """A model's :func:`discrepancy` to a measured set: one value per simulation draw (``draws``), and
    per measured trajectory its cross term averaged over the draws (``rows``: twice its mean
    distance to the simulated trajectories, summed over the discrepancy's parts).

    Two models scored against the same measured set differ by the mean of their ``rows``
    differences (the measured set's own within-sample term cancels) and by their simulated
    samples; the first is how the measured sample's own randomness enters a comparison.
    """

    draws: list[float]
    rows: Tensor = field(default_factory=lambda: torch.zeros(0))

    @property
    def mean(self) -> float:
        return float(torch.tensor(self.draws).mean())

    @property
    def finite(self) -> bool:
        return bool(torch.isfinite(torch.tensor(self.draws)).all())

    @classmethod
    def diverged(cls, repeats: int) -> Scores:
        """The scores of a model that diverges for some inputs: it does not describe the data."""
        return cls([float("inf")] * repeats)


@dataclass
class FittedTerms:
    """Terms with fitted priors, the family, the held-out scores, the training loss."""

    family: str
    candidates: list[Candidate]
    priors: list[Prior]
    heldout: Scores
    loss: list[float]
    start: list[float] = field(default_factory=list)  # where the fit started (refits for intervals start there too)
    scales: list[float] | None = None  # the coefficients' natural sizes the fit moved them in

    @property
    def heldout_energy(self) -> float:
        return self.heldout.mean

    def terms(self) -> list[LibraryTerm]:
        return [LibraryTerm(c.feature, c.component, prior) for c, prior in zip(self.candidates, self.priors)]

    def model(self, base: PhysicsModel) -> Augmented:
        return Augmented(base, self.terms())

    def as_record(self) -> dict:
        """Plain data (numbers, strings, lists, a tensor) that :meth:`from_record` turns back into these terms."""
        return {
            "family": self.family,
            "candidates": [[c.feature, c.component] for c in self.candidates],
            "priors": [[type(p).__name__, dict(p.init_args)] for p in self.priors],
            "heldout": {"draws": list(self.heldout.draws), "rows": self.heldout.rows},
            "loss": list(self.loss),
            "start": list(self.start),
            "scales": self.scales,
        }

    @classmethod
    def from_record(cls, record: dict) -> FittedTerms:
        candidates = [Candidate(feature, component) for feature, component in record["candidates"]]
        priors = [PRIOR_CLASSES[name](**arguments) for name, arguments in record["priors"]]
        heldout = Scores(list(record["heldout"]["draws"]), record["heldout"]["rows"])
        rest = (list(record["loss"]), list(record["start"]), record["scales"])
        return cls(record["family"], candidates, priors, heldout, *rest)


PRIOR_CLASSES = {prior.__name__: prior for prior in (Constant, Uniform, Normal, Choice)}  # the families' priors


class CoefficientPrior(torch.nn.Module):
    """A differentiable prior family over K coefficients, started at ``init``.

    The optimiser moves each coefficient in units of its ``scales`` (default: its start's size):
    a term whose start is far too small (a network that learned drag mostly as linear friction
    gives ``v*|v|`` a tiny slope) must still be able to reach its value.
    """

    def __init__(self, family: str, init: list[float], scales: list[float] | None = None) -> None:
        super().__init__()
        init = torch.tensor(init, dtype=torch.float32)
        scale = init.abs() if scales is None else torch.maximum(torch.tensor(scales, dtype=torch.float32), init.abs())
        self.family = family
        self.register_buffer("init", init)
        self.register_buffer("scale", torch.where(scale > 0, scale, torch.ones_like(init)))
        self.shift = torch.nn.Parameter(torch.zeros_like(init))
        self.raw_width = torch.nn.Parameter(torch.full_like(init, -2.0))

    @property
    def centre(self) -> Tensor:
        return self.init + self.scale * self.shift

    @property
    def width(self) -> Tensor:
        """Half-width (uniform, two-point) or standard deviation (normal); at least ``MIN_WIDTH`` scales, so that a fit
        that shrinks it to nothing (a coefficient that does not vary) still gives a valid prior."""
        return self.scale * (F.softplus(self.raw_width) + MIN_WIDTH)

    def draw(self, noise: Tensor) -> Tensor:
        """Coefficients (n, K) for standardised draws ``noise`` (n, K)."""
        return self.centre + (torch.zeros_like(noise) if self.family == "constant" else self.width * noise)

    def priors(self) -> list[Prior]:
        centre, width = self.centre.tolist(), self.width.tolist()
        if self.family == "constant":
            return [Constant(c) for c in centre]
        if self.family == "uniform":
            return [Uniform(c - w, c + w) for c, w in zip(centre, width)]
        if self.family == "two_point":
            return [Choice([c - w, c + w]) for c, w in zip(centre, width)]
        return [Normal(c, w) for c, w in zip(centre, width)]


def centre(prior: Prior) -> float:
    """The centre c of a fitted prior: the constant c, U(c - w, c + w), N(c, w^2) or {c - w, c + w}."""
    if isinstance(prior, Constant):
        return prior.value
    if isinstance(prior, Uniform):
        return (prior.low + prior.high) / 2
    if isinstance(prior, Normal):
        return prior.mean
    if isinstance(prior, Choice):
        return sum(prior.values) / len(prior.values)
    raise TypeError(f"centre: a Constant, Uniform, Normal or Choice prior, got {type(prior).__name__}")


def standard_noise(family: str, shape: tuple[int, ...], generator: torch.Generator) -> Tensor:
    """Draws that a prior family's centre + width * noise maps to coefficients: N(0, 1) (normal), -1 or 1 equally
    likely (two-point) or U(-1, 1)."""
    if family == "normal":
        return torch.randn(shape, generator=generator)
    uniform = 2 * torch.rand(shape, generator=generator) - 1
    return torch.where(uniform < 0, -1.0, 1.0) if family == "two_point" else uniform


@dataclass
class FitSample:
    """The fixed samples of one fit: measured targets (m, T, *obs), inputs of the simulated trajectories, coefficient noise."""

    targets: Tensor
    x0: Tensor
    theta: Tensor
    noise: Tensor

    @classmethod
    def draw(cls, base: PhysicsModel, measured: Tensor, family: str, terms: int, batch: int, seed: int) -> FitSample:
        g = torch.Generator().manual_seed(seed)
        targets = measured[torch.randperm(len(measured), generator=g)[:batch]].float()
        x0, theta = base.sample_initial_state(batch, g), base.sample_theta(batch, g)
        return cls(targets, x0, theta, standard_noise(family, (batch, terms), g))

    def to(self, device: torch.device) -> FitSample:
        return FitSample(*(t.to(device) for t in (self.targets, self.x0, self.theta, self.noise)))


def simulate_finite(model: Augmented, x0: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """Observed trajectories (n', T, *obs) of the augmented model without those that diverged (a coefficient
    that makes the model blow up, e.g. a growing cubic), and which of the n inputs diverged (n,)."""
    trajectories = model.observe(model.solve(model.vector_field, x0, theta))
    finite = torch.isfinite(trajectories.flatten(1)).all(1)
    return trajectories[finite], ~finite


def term_names(candidates: list[Candidate]) -> list[str]:
    return [f"{c.feature} on d{c.component}/dt" for c in candidates]


def discrepancy(a: Tensor, b: Tensor) -> Tensor:
    """Energy distance between trajectories a (n, T, *obs) and b (m, T, *obs): over whole trajectories
    plus the sum over time steps and components of the distances between their values there.

    The second part compares the marginal distributions at each time (a spread that grows or
    shrinks over time, as an effect that varies between trajectories makes it), which the
    distance between whole trajectories detects with far less power.
    """
    return discrepancy_and_rows(a, Target.of(b))[0]


def batched_discrepancy(a: Tensor, b: Tensor) -> Tensor:
    """:func:`discrepancy` of each pair a[g] (n, T, *obs), b[g] (m, T, *obs): (G,)."""
    whole = batched_energy(a.flatten(2), b.flatten(2))
    cells = lambda y: _cells(y.flatten(0, 1)).unflatten(1, y.shape[:2]).transpose(0, 1).flatten(0, 1)  # noqa: E731
    per_cell = batched_energy(cells(a), cells(b)).reshape(len(a), -1)
    return whole + per_cell.sum(1)


def _cells(y: Tensor) -> Tensor:
    """Trajectories (n, T, C, *space) as (T * C, n, space): one sample per time step and component."""
    return y.reshape(len(y), y.shape[1] * y.shape[2], -1).transpose(0, 1)


@dataclass
class Target:
    """Measured trajectories y (m, T, *obs) and their within-sample mean distances, whole (a number) and per cell
    (T * C,): every :func:`discrepancy` to them shares these, so they are computed once."""

    y: Tensor
    whole: Tensor
    cells: Tensor

    @classmethod
    def of(cls, y: Tensor) -> Target:
        whole, cells = _within(y)
        return cls(y, whole, cells)


def discrepancy_and_rows(a: Tensor, target: Target) -> tuple[Tensor, Tensor]:
    """:func:`discrepancy` of a to the target and, per target trajectory, its share of the cross terms
    (:func:`row_terms`), from one set of distances."""
    whole, cells = _cross(a, target.y)  # (m,), (T * C, m)
    within_whole, within_cells = _within(a)
    value = 2 * whole.mean() - within_whole - target.whole
    value = value + (2 * cells.mean(-1) - within_cells - target.cells).sum()
    return value, 2 * (whole + cells.sum(0))


def _cross(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Each trajectory of b's mean distance to a's, whole (m,) and per cell (T * C, m). On fields, both from one
    product per cell (:func:`otgb.metrics.energy.cell_and_whole_row_means`); a cell of one number is sorted."""
    if _on_fields(a):
        cells, whole = cell_and_whole_row_means(_cells(a), _cells(b))
        return whole, cells
    return cross_row_means(a.flatten(1)[None], b.flatten(1)[None])[0], cross_row_means(_cells(a), _cells(b))


def _within(y: Tensor) -> tuple[Tensor, Tensor]:
    """Mean distance between y's distinct trajectories, whole (a number) and per cell (T * C,), as :func:`_cross`."""
    if _on_fields(y):
        cells, whole = cell_and_whole_within_means(_cells(y))
        return whole, cells
    return within_means(y.flatten(1)[None])[0], within_means(_cells(y))


def _on_fields(y: Tensor) -> bool:
    """Whether a cell of y (n, T, C, *space) (one time step and component) holds more than one number."""
    return math.prod(y.shape[3:]) > 1


def row_terms(a: Tensor, b: Tensor) -> Tensor:
    """Per trajectory of b, its share of :func:`discrepancy`'s cross terms: twice its mean distance to
    a's trajectories, whole and per cell, summed: (m,)."""
    whole = cross_row_means(a.flatten(1)[None], b.flatten(1)[None])[0]
    return 2 * (whole + cross_row_means(_cells(a), _cells(b)).sum(0))


def fit(
    base: PhysicsModel,
    candidates: list[Candidate],
    init: list[float],
    family: str,
    measured: Tensor,
    heldout: Tensor,
    steps: int = 50,
    batch: int = 512,
    seed: int = 0,
    score: bool = True,
    scales: list[float] | None = None,
    device: torch.device = CPU,
) -> FittedTerms:
    """Fit the coefficients' prior of one ``family`` to ``measured`` (m, T, *obs); score on ``heldout`` (if ``score``).

    The simulated sample is held fixed during the fit (``batch`` trajectories, their inputs
    from the priors and the coefficients' noise drawn once; against at most ``batch`` measured
    ones), so the discrepancy is a smooth deterministic function of the prior's parameters and
    L-BFGS (``steps`` iterations, strong-Wolfe line search) can follow the narrow valleys that
    correlated terms make. Where its last step leaves the prior's parameters non-finite (a line search
    that ran into coefficients whose solves diverge), the fit keeps the best iterate it evaluated.
    It runs on ``device``; its draws are made on the CPU, the same on every device.
    """
    prior = CoefficientPrior(family, init, scales).to(device)
    terms = [LibraryTerm(c.feature, c.component, Constant(v)) for c, v in zip(candidates, init)]
    model = Augmented(on_device(base, device), terms).to(device)
    n = batch
    sample = FitSample.draw(base, measured, family, len(candidates), batch, seed).to(device)
    target, x0, theta, noise = Target.of(sample.targets), sample.x0, sample.theta, sample.noise
    optimiser = torch.optim.LBFGS(prior.parameters(), lr=1, max_iter=steps, max_eval=2 * steps, line_search_fn="strong_wolfe")
    losses: list[float] = []
    best: list[Tensor] = []  # the parameters of the lowest finite loss evaluated

    def simulate(rows: slice) -> Tensor:
        return model.observe(model.solve(model.vector_field, x0[rows], torch.cat([theta[rows], prior.draw(noise[rows])], 1)))

    size = chunk_size(simulate, n)

    def closure() -> Tensor:
        optimiser.zero_grad()
        loss, _ = backward_in_chunks(simulate, n, lambda simulated: discrepancy_and_rows(simulated, target)[0], size)
        if not torch.isfinite(loss):  # trajectories diverged, or grew so large that their distances overflow
            return torch.tensor(DIVERGED_LOSS)
        value = float(loss)
        if not losses or value < min(losses):
            best[:] = [p.detach().clone() for p in prior.parameters()]
        losses.append(value)
        return loss

    optimiser.step(closure)
    if losses and not prior_is_finite(prior):
        with torch.no_grad():
            for parameter, value in zip(prior.parameters(), best):
                parameter.copy_(value)
    if not losses or not prior_is_finite(prior):
        diverged(f"fit ({family})", term_names(candidates), n, n)
        priors = [Constant(v) for v in init]
        return FittedTerms(family, list(candidates), priors, Scores.diverged(HELDOUT_REPEATS), losses, list(init), scales)
    priors = prior.priors()
    scored = discrepancies(base, candidates, priors, heldout, seed, device=device) if score else Scores([])
    return FittedTerms(family, list(candidates), priors, scored, losses, list(init), scales)


def on_device(physics: PhysicsModel, device: torch.device) -> PhysicsModel:
    """``physics`` itself on the CPU; elsewhere a copy moved to ``device`` (moving a module moves it in place, and the rest
    of discovery uses it on the CPU), in its current state (the measurement noise in force)."""
    return physics if device.type == "cpu" else copy.deepcopy(physics).to(device)


def prior_is_finite(prior: CoefficientPrior) -> bool:
    return bool(torch.isfinite(prior.centre).all() and torch.isfinite(prior.width).all())


@dataclass
class Fitting:
    """How every coefficient fit of one discovery run is made (:func:`fit`): on the training part, scored on the
    validation part, with one run's steps, batch and seed; each coefficient moved in units of its natural scale
    (``natural``: the slope at which its term alone is as large as f_phi) where one is known."""

    physics: PhysicsModel
    train: Tensor
    val: Tensor
    steps: int
    batch: int
    seed: int
    natural: dict[Candidate, float] = field(default_factory=dict)
    cache: FitCache | None = None  # finished fits on disk (:mod:`otgb.discovery.fit_cache`)
    device: torch.device = CPU  # where the fits run; the CPU from the first fit that fails elsewhere (:meth:`fit_on_device`)
    fallback: str | None = None  # why the fits moved to the CPU

    def __call__(self, candidates: list[Candidate], init: list[float], family: str = "constant", natural_scales: bool = True):
        """The fitted prior of ``family`` for ``candidates`` started at ``init``; without ``natural_scales`` each
        coefficient moves in units of its start's size. Read from the cache where it holds this fit."""
        scales = [float(self.natural[c]) for c in candidates] if natural_scales and self.natural else None
        init = [float(v) for v in init]

        def run() -> FittedTerms:
            data = (self.train, self.val, self.steps, self.batch, self.seed)
            return self.fit_on_device(lambda on: fit(self.physics, candidates, init, family, *data, scales=scales, device=on))

        if self.cache is None:
            return run()
        terms = [(c.feature, c.component) for c in candidates]
        inputs = {"terms": terms, "init": init, "family": family, "scales": scales, "steps": self.steps, "batch": self.batch}
        inputs |= {"device": device_name(self.device), "solver": current_solver()}  # each rounds differently

        def stored() -> dict:
            before = self.device
            fitted = run()
            return {"fitted": fitted.as_record(), "fallback": self.fallback if self.device != before else None}

        record = self.cache.record(self.cache.key(self.physics, self.train, self.val, seed=self.seed, **inputs), stored)
        if record["fallback"] is not None and self.device.type != "cpu":  # the run that made this fit moved to the CPU here
            self.fall_back(record["fallback"])
        return FittedTerms.from_record(record["fitted"])

    def fit_on_device(self, fit_on: Callable[[torch.device], FittedTerms]) -> FittedTerms:
        """``fit_on(self.device)``; where it fails off the CPU, one warning and this and every later fit on the CPU (the
        divergences the failed attempt logged are dropped: the CPU's fit logs its own)."""
        if self.device.type == "cpu":
            return fit_on(self.device)
        try:
            with held_divergences() as held:
                fitted = fit_on(self.device)
        except RuntimeError as error:  # torch.cuda.OutOfMemoryError included
            self.fall_back(f"a fit on {self.device} failed ({error})")
            return fit_on(self.device)
        say_again(held)
        return fitted

    def fall_back(self, reason: str) -> None:
        logger.warning(f"discover: the coefficient fits run on the CPU: {reason}")
        self.device, self.fallback = CPU, reason


def device_name(device: torch.device) -> str:
    """``cpu``, or the type and model of a CUDA device (another model rounds differently)."""
    return f"{device.type}:{torch.cuda.get_device_name(device)}" if device.type == "cuda" else device.type


@torch.no_grad()
def discrepancies(
    base: PhysicsModel,
    candidates: list[Candidate],
    priors: list[Prior],
    measured: Tensor,
    seed: int,
    repeats: int = HELDOUT_REPEATS,
    device: torch.device = CPU,
) -> Scores:
    """:class:`Scores` to ``measured`` of ``repeats`` fresh simulation draws as large as it, coefficients from ``priors``.

    The inputs and the coefficients' noise come from two generators seeded alike for every
    model, so that two models' scores differ by their coefficients, not by the luck of the
    draws (common random numbers): their difference is then measured far more precisely.
    """
    terms = [LibraryTerm(c.feature, c.component, Constant(0.0)) for c in candidates]
    model = Augmented(on_device(base, device), terms).to(device)
    inputs, noise = torch.Generator().manual_seed(seed + 1), torch.Generator().manual_seed(seed + 2)
    n, values, rows = len(measured), [], torch.zeros(len(measured), dtype=torch.float64, device=device)
    target = Target.of(measured.double().to(device))
    for _ in range(repeats):
        x0, theta = base.sample_initial_state(n, inputs), base.sample_theta(n, inputs)
        coefficients = (
            torch.stack([p.quantile(torch.rand(n, generator=noise)) for p in priors], 1) if priors else torch.zeros(n, 0)
        )
        simulated, bad = simulate_finite(model, x0.to(device), torch.cat([theta, coefficients.float()], dim=1).to(device))
        if bad.any():
            first = int(bad.nonzero()[0])
            diverged("score", term_names(candidates), int(bad.sum()), n, theta[first].tolist(), list(map(repr, priors)))
            return Scores.diverged(repeats)
        value, row = discrepancy_and_rows(simulated.double(), target)
        values.append(float(value))
        rows += row / repeats
    return Scores(values, rows.cpu())


@torch.no_grad()
def sample_scores(draw: Callable[[int], Tensor], measured: Tensor, repeats: int) -> Scores:
    """:class:`Scores` to ``measured`` of ``repeats`` samples ``draw(r)`` of any model (a grey-box, f_p)."""
    values, rows, target = [], torch.zeros(len(measured), dtype=torch.float64), Target.of(measured.double())
    for r in range(repeats):
        value, row = discrepancy_and_rows(draw(r).double(), target)
        values.append(float(value))
        rows += row / repeats
    return Scores(values, rows)


def difference(a: Scores, b: Scores) -> tuple[float, float]:
    """b's discrepancy minus a's (positive: a fits better), and the standard error of that difference.

    Two sources of error, independent: the simulation draws (the paired differences' spread over
    the draws, common random numbers) and the measured sample, which is finite, and the same for
    both (the spread over measured trajectories of the differences of their ``rows``): a model may
    fit these measured trajectories better than another without describing the process better.
    A model that diverged is infinitely worse.
    """
    if not (a.finite and b.finite):
        return (float("inf") if a.finite else float("-inf") if b.finite else float("nan")), float("nan")
    differences = torch.tensor(b.draws) - torch.tensor(a.draws)
    variance = differences.var() / len(differences)
    if len(a.rows) > 1 and len(a.rows) == len(b.rows):
        variance = variance + (b.rows - a.rows).var() / len(a.rows)
    return float(differences.mean()), float(variance) ** 0.5


def beats(a: Scores, b: Scores) -> bool:
    """Whether model a's discrepancy is lower than b's by more than two standard errors of the difference
    (:func:`difference`)."""
    gap, error = difference(a, b)
    if not math.isfinite(gap):
        return gap == float("inf")
    resolution = 1e-9 * abs(b.mean)  # below float rounding: a tie, e.g. a term fitted to zero
    return gap > 2 * error + resolution
