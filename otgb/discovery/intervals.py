"""95 % intervals of fitted coefficients (and of their spread): the sandwich of the fit's own discrepancy.

A fit (:func:`otgb.discovery.refine.fit`) minimises L(p), the discrepancy between a fixed
simulated sample (n trajectories, their inputs and coefficient noise drawn once) and the
measured targets (m trajectories), over the prior's parameters p (each term's centre, and
its half-width or standard deviation for a family that varies). Its estimate moves with both
samples. The gradient of L is a two-sample U-statistic, so to first order

    Var(grad L) = Cov_j(a_j) / m + Cov_i(b_i) / n,

with a_j the derivative of measured trajectory j's cross terms (twice its mean distance to
the simulated ones) and b_i that of simulated trajectory i's terms (twice its mean distance to
the measured ones minus twice its mean distance to the other simulated ones), and

    Var(p_hat) = H^-1 Var(grad L) H^-1,   H the Hessian of L at p_hat

(the sandwich, or delta method, of an M-estimator). The interval is p_hat +- 1.96 standard
errors: it contains the estimate by construction, covers both the measured sample's and the
fit's own simulation error, and costs one solve instead of a refit per resample (30 full
refits of a pendulum fit took 5.4 min on 2 cores; this takes seconds). The derivatives are
central differences over p (the gradients by autograd, the per-trajectory terms by their
values) on one batched solve with the fit's own samples. An asymptotic interval: its coverage
of the truth is measured on fresh files by ``scripts/interval_coverage.py`` (docs/discovery.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from otgb.data.gaps import comparable, filled
from otgb.discovery.chunked import Simulate, backward_in_chunks, chunk_size
from otgb.discovery.discrepancy import batched_discrepancy, row_terms
from otgb.discovery.families import centre, spread, varies
from otgb.discovery.log import diverged
from otgb.discovery.refine import FitSample, FittedTerms, Fitting
from otgb.discovery.scores import term_names
from otgb.discovery.stages import stage
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel
from otgb.physics.priors import Constant
from otgb.physics.solvers import current_solver
from otgb.physics.terms import LibraryTerm

Z95 = 1.959964
STEP = 1e-2  # central-difference step, in units of each parameter's size


@dataclass
class Intervals:
    """Per coefficient: the 95 % interval of its centre, and of its spread (families that vary; else None)."""

    centre: list[tuple[float, float]]
    width: list[tuple[float, float]] | None
    method: str = "estimate +- 1.96 sandwich standard errors of the distribution-matching fit"


def parameters(fitted: FittedTerms) -> Tensor:
    """p: the centres, then (families that vary) the half-widths (uniform, two-point) or standard deviations (normal)."""
    centres = [centre(prior) for prior in fitted.priors]
    if not varies(fitted.family):
        return torch.tensor(centres, dtype=torch.float64)
    return torch.tensor(centres + [spread(prior) for prior in fitted.priors], dtype=torch.float64)


def sandwich_intervals(base: PhysicsModel, fitted: FittedTerms, measured: Tensor, batch: int, seed: int) -> Intervals | None:
    """:class:`Intervals` of ``fitted`` (fitted to ``measured`` with ``batch`` and ``seed``); None if they cannot be
    computed (a perturbed model diverges, or the Hessian is not positive definite: the fit is not at a minimum)."""
    p = parameters(fitted)
    covariance = sandwich_covariance(base, fitted, p, measured, batch, seed)
    if covariance is None:
        return None
    errors = covariance.diagonal().clamp_min(0).sqrt()
    low, high = (p - Z95 * errors).tolist(), (p + Z95 * errors).tolist()
    k = len(fitted.candidates)
    centre = list(zip(low[:k], high[:k]))
    width = None if not varies(fitted.family) else [(max(a, 0.0), b) for a, b in zip(low[k:], high[k:])]
    return Intervals(centre, width)


@stage("intervals")
def fitted_intervals(fitting: Fitting, fitted: FittedTerms) -> Intervals | None:
    """:func:`sandwich_intervals` of one of a discovery run's fits (on its training part, with its batch and seed), kept
    in the run's fit cache where it has one: a model asked about twice (the search's kept model is often the final one)
    or again by a resumed run is computed once (a reaction-diffusion model's take minutes)."""

    def compute() -> Intervals | None:
        return sandwich_intervals(fitting.physics, fitted, fitting.train, fitting.batch, fitting.seed)

    if fitting.cache is None:
        return compute()
    model = {k: v for k, v in fitted.as_record().items() if k in ("family", "candidates", "priors", "scales", "samples")}
    inputs = {"intervals_of": model, "batch": fitting.batch, "solver": current_solver()}
    key = fitting.cache.key(fitting.physics, fitting.train, fitting.val, seed=fitting.seed, **inputs)
    stored = fitting.cache.record(key, lambda: {"intervals": None if (found := compute()) is None else asdict(found)})
    return None if stored["intervals"] is None else Intervals(**stored["intervals"])


def sandwich_covariance(
    base: PhysicsModel, fitted: FittedTerms, p: Tensor, measured: Tensor, batch: int, seed: int
) -> Tensor | None:
    """H^-1 Var(grad L) H^-1 at p (module docstring), or None."""
    sample = FitSample.draw(base, measured, fitted.family, len(fitted.candidates), batch, seed, fitted.samples)
    steps = STEP * _sizes(fitted, p)
    simulator = lambda variants: _simulator(base, fitted, variants, sample)  # noqa: E731
    covariance = sandwich(p, steps, simulator, sample.targets.double(), len(sample.x0), sample.samples)
    if covariance is None:
        return None
    if isinstance(covariance, int):  # trajectories of a perturbed model diverged
        diverged("interval", term_names(fitted.candidates), covariance, (1 + 2 * len(p)) * len(sample.x0), None)
        return None
    return covariance


def sandwich(
    p: Tensor, steps: Tensor, simulator: Callable[[Tensor], Simulate], targets: Tensor, n: int, samples: int = 1
) -> Tensor | int | None:
    """H^-1 Var(grad L) H^-1 at p of a fit's discrepancy L (module docstring), from central differences of ``steps``:
    ``simulator(variants)`` gives the trajectories of the flattened (variant, trajectory) grid, n (``samples`` samples)
    per variant, compared with ``targets``. The number of diverged trajectories where any diverged; None where the
    loss is not finite or the Hessian not positive definite (not at a minimum)."""
    variants = torch.cat([p[None], p + torch.diag(steps), p - torch.diag(steps)]).requires_grad_()  # (1 + 2P, P)
    V = len(variants)

    def losses(simulated: Tensor) -> Tensor:  # the sum over the variants of these rows of each one's mean discrepancy
        grouped = simulated.unflatten(0, (-1, n // samples))  # one group per variant and sample
        return batched_discrepancy(grouped, targets.expand(len(grouped), *targets.shape)).sum() / samples

    simulate = simulator(variants)
    total, simulated = backward_in_chunks(simulate, V * n, losses, chunk_size(simulate, V * n), groups=V)
    finite = torch.isfinite(simulated.flatten(1)).all(1)
    if not bool(finite.all()):
        return int((~finite).sum())
    if not bool(torch.isfinite(total)):
        return None
    gradients = variants.grad  # row v: grad L at variants[v]
    simulated = simulated.unflatten(0, (V, n))
    P = len(p)
    hessian = (gradients[1 : 1 + P] - gradients[1 + P :]) / (2 * steps[:, None])
    hessian = (hessian + hessian.T) / 2
    if not bool(torch.linalg.eigvalsh(hessian).min() > 0):
        return None
    a, b = _influences(simulated[1 : 1 + P], simulated[1 + P :], targets, steps, samples)
    variance = _covariance(a) / len(a) + _covariance(b) / len(b)
    inverse = torch.linalg.inv(hessian)
    return inverse @ variance @ inverse


def _sizes(fitted: FittedTerms, p: Tensor) -> Tensor:
    """Each parameter's size: its value, or its term's natural scale where that is larger (widths share their term's)."""
    scales = torch.tensor(fitted.scales or [0.0] * len(fitted.candidates), dtype=torch.float64)
    sizes = torch.maximum(p.abs(), scales.repeat(len(p) // len(scales)))
    return torch.where(sizes > 0, sizes, torch.ones_like(sizes))


def _covariance(rows: Tensor) -> Tensor:
    """The covariance (P, P) of rows (N, P)."""
    centred = rows - rows.mean(0)
    return centred.T @ centred / (len(rows) - 1)


def _simulator(base: PhysicsModel, fitted: FittedTerms, variants: Tensor, sample: FitSample) -> Simulate:
    """The trajectories (rows, T, *obs) of rows of the flattened (variant, trajectory) grid: the fitted terms with
    ``variants[v]`` as p, the fit's inputs and noise of trajectory i, at row v * n + i."""
    model = Augmented(base, [LibraryTerm(c.feature, c.component, Constant(0.0)) for c in fitted.candidates])
    k, n = len(fitted.candidates), len(sample.x0)

    def simulate(rows: slice) -> Tensor:
        index = torch.arange(len(variants) * n)[rows]
        variant, trajectory = variants[index // n], index % n
        widths = variant[:, k:] if varies(fitted.family) else torch.zeros_like(variant[:, :k])
        coefficients = variant[:, :k] + widths * sample.noise.double()[trajectory]
        theta = torch.cat([sample.theta[trajectory], coefficients.float()], 1)
        signals = sample.signals_of(trajectory)
        return model.observe(model.solve(model.vector_field, sample.x0[trajectory], theta, signals=signals)).double()

    return simulate


def _pair_terms(s: Tensor, y: Tensor, samples: int = 1) -> tuple[Tensor, Tensor]:
    """For simulated s (n, T, *obs) and measured y (m, T, *obs): each measured trajectory's terms (twice its mean
    distance to the simulated ones) (m,), and each simulated one's (twice its mean distance to the measured minus
    twice its mean distance to the other simulated ones) (n,), over the discrepancy's parts (:func:`row_terms`). Where
    s holds ``samples`` independent samples (a fit's mean over them, ``discover.spread_samples``), a
    simulated trajectory's terms are within its own sample and a measured one's are averaged over the samples."""
    blocks = [comparable(block, y)[0] for block in s.chunk(samples)]  # each sample with y's gaps (otgb.data.gaps)
    y = filled(y)
    measured = torch.stack([row_terms(block, y) for block in blocks]).mean(0)
    simulated = [row_terms(y, block) - row_terms(block, block) * len(block) / (len(block) - 1) for block in blocks]
    return measured, torch.cat(simulated)


def _influences(plus: Tensor, minus: Tensor, targets: Tensor, steps: Tensor, samples: int = 1) -> tuple[Tensor, Tensor]:
    """a (m, P) and b (n, P): the central-difference derivatives of each trajectory's terms in p."""
    a, b = [], []
    for k in range(len(steps)):
        measured_plus, simulated_plus = _pair_terms(plus[k], targets, samples)
        measured_minus, simulated_minus = _pair_terms(minus[k], targets, samples)
        a.append((measured_plus - measured_minus) / (2 * steps[k]))
        b.append((simulated_plus - simulated_minus) / (2 * steps[k]))
    return torch.stack(a, 1), torch.stack(b, 1)
