"""Add: fit the named terms' coefficients, and their prior, by matching distributions.

The augmented physics f_p + sum_k c_k feature_k (:class:`otgb.physics.Augmented`) is a
differentiable simulator; its coefficients, or the parameters of their prior, are fitted so
that its trajectories (inputs from f_p's priors) match the measured training trajectories in
the unbiased energy distance (:mod:`otgb.metrics.energy`; no bandwidth to tune, unbiased, so
it is 0 on average at the optimum whatever the batch size), between whole trajectories and
between the values at each time step (:func:`otgb.discovery.discrepancy.discrepancy`), in one prior family per fit
(:mod:`otgb.discovery.families`).

:mod:`otgb.discovery.variation` decides between them (a richer family only if it lowers the
discrepancy by more than two standard errors, over simulation draws with common random numbers,
:func:`otgb.discovery.scores.discrepancies`), so whether the effect varies is decided by the data. The families are
compared on the training measurements: the richer families add one width per term to hundreds of
trajectories, too little to fit noise, and the training part is several times larger than the
held-out parts, which a spread that varies over time needs to be seen.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from otgb.discovery.crossfit import Folds, cross_fitted, heldout_part, refit_steps
from otgb.discovery.discrepancy import Target
from otgb.discovery.families import CONSTANT, centre, prior, standard_noise, varies
from otgb.discovery.fit_cache import FitCache
from otgb.discovery.lbfgs import Curvature, Ended, minimise
from otgb.discovery.library import Candidate
from otgb.discovery.log import diverged, held_divergences, logger, say_again
from otgb.discovery.scores import CPU, HELDOUT_REPEATS, Scores, discrepancies, on_device, term_names
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel
from otgb.physics.priors import Choice, Constant, Normal, Prior, Uniform
from otgb.physics.solvers import current_solver
from otgb.physics.terms import LibraryTerm

FAMILY_REPEATS = 20  # simulation draws per score of a prior family on the training measurements
MIN_WIDTH = 1e-6  # a prior's smallest width, in units of its coefficient's scale
START_RAW_WIDTH = -2.0  # where a fit's raw width parameter starts: a width of softplus(-2) = 0.13 scales
# Independent simulated samples a fit of a family that varies averages its discrepancy over, by default
# (``discover.spread_samples``). A spread changes the
# discrepancy at second order in its width, by less than one fixed sample's own noise: fitted on one sample of 1024
# (a pendulum drag varying as U(-0.75, -0.25), 2000 measured trajectories), the half-width came out 0.06, 0.20 or
# 0.30 with the sample's seed, and 0 from the constant's optimum; on the mean over 4 samples, 0.27, 0.26 and 0.24.
SPREAD_SAMPLES = 4


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
    samples: int = 1  # simulated samples the fit averaged its discrepancy over (``discover.spread_samples``)
    fold_priors: list[list[Prior]] = field(default_factory=list)  # per fold, the priors of its cross-fitting refit
    ended: Ended | None = field(default=None, repr=False, compare=False)  # where its fit ended (not in its record)

    @property
    def centres(self) -> list[float]:
        return [centre(p) for p in self.priors]

    @property
    def refit_scales(self) -> list[float]:
        """The units a refit from its centres moves the coefficients in: those its fit moved them in."""
        n = len(self.candidates)
        return [max(abs(v), s) for v, s in zip(self.start or [0.0] * n, self.scales or [0.0] * n)]

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
            "heldout": {"draws": list(self.heldout.draws), "rows": self.heldout.rows, "folds": self.heldout.folds},
            "loss": list(self.loss),
            "start": list(self.start),
            "scales": self.scales,
            "samples": self.samples,
            "fold_priors": [[[type(p).__name__, dict(p.init_args)] for p in fold] for fold in self.fold_priors],
        }

    @classmethod
    def from_record(cls, record: dict) -> FittedTerms:
        candidates = [Candidate(feature, component) for feature, component in record["candidates"]]
        priors = [PRIOR_CLASSES[name](**arguments) for name, arguments in record["priors"]]
        heldout = Scores(list(record["heldout"]["draws"]), record["heldout"]["rows"], record["heldout"].get("folds", 1))
        rest = (list(record["loss"]), list(record["start"]), record["scales"], record.get("samples", 1))
        folds = [[PRIOR_CLASSES[name](**arguments) for name, arguments in fold] for fold in record.get("fold_priors", [])]
        return cls(record["family"], candidates, priors, heldout, *rest, folds)


PRIOR_CLASSES = {prior.__name__: prior for prior in (Constant, Uniform, Normal, Choice)}  # the families' priors


class CoefficientPrior(torch.nn.Module):
    """A differentiable prior family over K coefficients, started at centres ``init`` and widths of
    :data:`START_RAW_WIDTH`.

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
        self.raw_width = torch.nn.Parameter(torch.full_like(init, START_RAW_WIDTH))

    def widen_to_start(self) -> CoefficientPrior:
        """This prior, its widths made no narrower than a fit's start (a refit from where it ended: a width near zero
        barely moves, the softplus that keeps it positive is flat there)."""
        self.raw_width.data.clamp_(min=START_RAW_WIDTH)
        return self

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
        return self.centre + (self.width * noise if varies(self.family) else torch.zeros_like(noise))

    def priors(self) -> list[Prior]:
        return [prior(self.family, c, w) for c, w in zip(self.centre.tolist(), self.width.tolist())]


@dataclass
class FitSample:
    """The fixed samples of one fit: measured targets (m, T, *obs), inputs of the simulated trajectories (x0, theta and
    a driven model's input signals), coefficient noise; ``samples`` independent simulated samples of equal size, one
    after the other."""

    targets: Tensor
    x0: Tensor
    theta: Tensor
    noise: Tensor
    samples: int = 1
    signals: Tensor | None = None

    def signals_of(self, rows: slice | Tensor) -> Tensor | None:
        """The input signals of ``rows`` of the simulated trajectories (None: the model is not driven)."""
        return None if self.signals is None else self.signals[rows]

    @classmethod
    def draw(
        cls, base: PhysicsModel, measured: Tensor, family: str, terms: int, batch: int, seed: int, samples: int = 1
    ) -> FitSample:
        """``samples`` samples of ``batch`` simulated trajectories, against as many measured ones (at most all)."""
        g = torch.Generator().manual_seed(seed)
        n = batch * samples
        targets = measured[torch.randperm(len(measured), generator=g)[:n]].float()
        x0, theta = base.sample_initial_state(n, g), base.sample_theta(n, g)
        noise = standard_noise(family, (n, terms), g)
        return cls(targets, x0, theta, noise, samples, base.sample_signals(n, g))

    def to(self, device: torch.device) -> FitSample:
        signals = None if self.signals is None else self.signals.to(device)
        return FitSample(*(t.to(device) for t in (self.targets, self.x0, self.theta, self.noise)), self.samples, signals)


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
    samples: int = 1,
    ended: Ended | None = None,
) -> FittedTerms:
    """Fit the coefficients' prior of one ``family`` to ``measured`` (m, T, *obs); score on ``heldout`` (if ``score``).

    The simulated sample is held fixed during the fit (``batch`` trajectories, their inputs
    from the priors and the coefficients' noise drawn once; against at most ``batch`` measured
    ones; with ``samples`` > 1, the mean discrepancy of that many such samples against as many
    measured ones, ``discover.spread_samples`` for a family that varies), so the discrepancy is a
    smooth deterministic function of the prior's parameters and L-BFGS (``steps`` iterations,
    strong-Wolfe line search) can follow the narrow valleys that correlated terms make. Where its
    last step leaves the prior's parameters non-finite (a line search that ran into coefficients
    whose solves diverge), the fit keeps the best iterate it evaluated. It runs on ``device``; its
    draws are made on the CPU, the same on every device. From ``ended`` (a fold's refit, :mod:`otgb.discovery.crossfit`)
    the fit starts where that one ended (:meth:`CoefficientPrior.widen_to_start`), with its optimiser's curvature
    (:class:`otgb.discovery.lbfgs.Curvature`); ``init`` and ``scales`` are then the ended fit's."""
    if ended is None:
        prior, curvature = CoefficientPrior(family, init, scales), Curvature()
    else:
        prior, curvature = ended.restart()
        prior.widen_to_start()
    prior = prior.to(device)
    terms = [LibraryTerm(c.feature, c.component, Constant(v)) for c, v in zip(candidates, init)]
    sample = FitSample.draw(base, measured, family, len(candidates), batch, seed, samples).to(device)
    model, n = Augmented(on_device(base, device), terms).to(device), len(sample.x0)
    target, x0, theta, noise = Target.of(sample.targets), sample.x0, sample.theta, sample.noise

    def simulate(rows: slice) -> Tensor:
        theta_of_rows = torch.cat([theta[rows], prior.draw(noise[rows])], 1)
        return model.observe(model.solve(model.vector_field, x0[rows], theta_of_rows, signals=sample.signals_of(rows)))

    parameters, is_finite = list(prior.parameters()), lambda: prior_is_finite(prior)
    losses = minimise(parameters, simulate, n, target, samples, steps, is_finite, curvature)
    if not losses or not prior_is_finite(prior):
        return _diverged_fit(family, candidates, init, losses, scales, samples, n)
    priors = prior.priors()
    scored = discrepancies(base, candidates, priors, heldout, seed, device=device) if score else Scores([])
    fitted = FittedTerms(family, list(candidates), priors, scored, losses, list(init), scales, samples)
    return replace(fitted, ended=Ended(prior, curvature))


def _diverged_fit(
    family: str, candidates: list[Candidate], init: list[float], losses: list[float], scales: list[float] | None,
    samples: int, n: int,
) -> FittedTerms:  # fmt: skip
    """The record of a fit whose model diverged (logged): its start's constants, scored as diverged."""
    diverged(f"fit ({family})", term_names(candidates), n, n)
    priors, failed = [Constant(v) for v in init], Scores.diverged(HELDOUT_REPEATS)
    return FittedTerms(family, list(candidates), priors, failed, losses, list(init), scales, samples)


def prior_is_finite(prior: CoefficientPrior) -> bool:
    return bool(torch.isfinite(prior.centre).all() and torch.isfinite(prior.width).all())


@dataclass
class Fitting:
    """How every coefficient fit of one discovery run is made (:func:`fit`): on the training part, scored on the
    validation part or, with ``folds``, cross-fitted over the folds of both (:mod:`otgb.discovery.crossfit`), with one
    run's steps, batch and seed; each coefficient moved in units of its natural scale (``natural``: the slope at which
    its term alone is as large as f_phi) where one is known."""

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
    spread_samples: int = SPREAD_SAMPLES  # simulated samples of a fit of a family that varies
    folds: Folds | None = None  # the folds held-out scores are cross-fitted over (None: scored on the validation part)

    def __call__(
        self, candidates: list[Candidate], init: list[float], family: str = CONSTANT, natural_scales: bool = True,
        samples: int | None = None,
    ) -> FittedTerms:  # fmt: skip
        """The fitted prior of ``family`` for ``candidates`` started at ``init``, on ``samples`` simulated samples
        (default: ``spread_samples`` for a family that varies, else one); without ``natural_scales`` each coefficient
        moves in units of its start's size. Read from the cache where it holds this fit."""
        scales = [float(self.natural.get(c, 0.0)) for c in candidates] if natural_scales and self.natural else None
        init, samples = [float(v) for v in init], samples or (self.spread_samples if varies(family) else 1)

        def run() -> FittedTerms:
            data = (self.train, self.val, self.steps, self.batch, self.seed)
            options = {"scales": scales, "samples": samples, "score": self.folds is None}
            fitted = self.fit_on_device(lambda on: fit(self.physics, candidates, init, family, *data, device=on, **options))
            return fitted if self.folds is None else self.cross_fitted(fitted)

        if self.cache is None:
            return run()
        terms = [(c.feature, c.component) for c in candidates]
        inputs = {"terms": terms, "init": init, "family": family, "scales": scales, "steps": self.steps, "batch": self.batch}
        inputs |= {"samples": samples, "folds": self.folds.k if self.folds else 1}
        inputs |= {"refit_steps": refit_steps(self.steps)} if self.folds else {}
        inputs |= {"device": device_name(self.device), "solver": current_solver()}  # each rounds differently

        def stored() -> dict:
            before = self.device
            fitted = run()
            return {"fitted": fitted.as_record(), "fallback": self.fallback if self.device != before else None}

        record = self.cache.record(self.cache.key(self.physics, self.train, self.val, seed=self.seed, **inputs), stored)
        if record["fallback"] is not None and self.device.type != "cpu":  # the run that made this fit moved to the CPU here
            self.fall_back(record["fallback"])
        return FittedTerms.from_record(record["fitted"])

    def cross_fitted(self, fitted: FittedTerms) -> FittedTerms:
        """``fitted`` with its held-out scores cross-fitted over the folds: the same fit (its family, scales and samples)
        on each fold's complement, started where ``fitted`` ended, :func:`~otgb.discovery.crossfit.refit_steps`
        iterations, scored on the fold; each fold's refit priors kept (:attr:`FittedTerms.fold_priors`)."""
        if not fitted.heldout.finite:
            return replace(fitted, heldout=Scores.diverged(HELDOUT_REPEATS, self.folds.k))
        ends: list[list[Prior]] = []

        def score_fold(k: int, rest: Tensor, held_out: Tensor) -> Scores:
            refit = self.fit_on_device(lambda on: refit_on(self.physics, fitted, rest, held_out, self, on))
            ends.append(refit.priors)
            return refit.heldout

        return replace(fitted, heldout=cross_fitted(self.folds, score_fold), fold_priors=ends)

    def alone(self) -> Scores:
        """The held-out scores of this fitting's physics with nothing fitted: on the validation part, or on each fold,
        as a fitted model's are (the same draws)."""
        score = lambda k, rest, fold: discrepancies(self.physics, [], [], fold, self.seed, device=self.device)  # noqa: E731
        return score(0, self.train, self.val) if self.folds is None else cross_fitted(self.folds, score)

    @property
    def heldout_part(self) -> str:
        """What a held-out score is on, in a log line's words (:func:`otgb.discovery.crossfit.heldout_part`)."""
        return heldout_part(self.folds is not None)

    def evidence_on(self) -> str | None:
        """What the held-out scores are cross-fitted over, for the log and the report; None without folds."""
        if self.folds is None:
            return None
        return f"the {len(self.folds.pool)} training and validation trajectories, cross-fitted over {self.folds.k} folds"

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


def refit_on(
    physics: PhysicsModel, fitted: FittedTerms, rest: Tensor, held_out: Tensor, fitting: Fitting,
    device: torch.device = CPU,
) -> FittedTerms:  # fmt: skip
    """``fitted`` fitted again to ``rest`` on ``physics`` (a fold's refit, :mod:`otgb.discovery.crossfit`): its family,
    scales and samples, from where its fit ended (its centres, where it was read from the fit cache),
    :func:`~otgb.discovery.crossfit.refit_steps` iterations with ``fitting``'s batch and seed; scored on ``held_out``."""
    data = (rest, held_out, refit_steps(fitting.steps), fitting.batch, fitting.seed)
    init, scales = (fitted.start, fitted.scales) if fitted.ended else (fitted.centres, fitted.refit_scales)
    options = {"scales": scales, "samples": fitted.samples, "ended": fitted.ended, "device": device}
    return fit(physics, fitted.candidates, init, fitted.family, *data, **options)


def device_name(device: torch.device) -> str:
    """``cpu``, or the type and model of a CUDA device (another model rounds differently)."""
    return f"{device.type}:{torch.cuda.get_device_name(device)}" if device.type == "cuda" else device.type
