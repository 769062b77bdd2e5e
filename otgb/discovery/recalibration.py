"""Recalibration: are f_p's parameters' priors off, rather than (or beside) a term missing?

A physicist's first question of a disagreement is whether the model is wrong or its parameters are. Here the
priors of theta are refitted, each in the family the config gave it, by the distribution matching that fits the
coefficients (:mod:`otgb.discovery.refine`): with theta_k = c_k + w_k s_k for fixed standard draws s_k (U(-1, 1) for
a uniform prior U(c - w, c + w), N(0, 1) for a normal N(c, w^2); a constant is c), the centres and widths minimise
the mean discrepancy of ``discover.spread_samples`` simulated samples to the training part (a
prior's width is a spread, which one sample's noise hides). The fit is scored on the validation part (with
``discover.folds`` > 1, cross-fitted over the held-out folds), and its 95 %
intervals are the sandwich of :mod:`otgb.discovery.intervals`. Priors of other kinds (a choice of values) are kept
as they are and said so.

f_p with the recalibrated priors is then weighed against f_p alone and against f_p plus the named terms on the
same held-out part (:mod:`otgb.discovery.verdict` words it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from otgb.discovery.chunked import Simulate
from otgb.discovery.crossfit import Folds, cross_fitted, heldout_part, refit_steps
from otgb.discovery.discrepancy import Target
from otgb.discovery.families import CONSTANT, NORMAL, UNIFORM, centre, prior, spread, standard_noise, varies
from otgb.discovery.intervals import STEP, Z95, sandwich
from otgb.discovery.lbfgs import Curvature, Ended, minimise
from otgb.discovery.prior_text import prior_text
from otgb.discovery.scores import HELDOUT_REPEATS, Scores, clears, difference, discrepancies
from otgb.physics.base import FieldModel, PhysicsModel
from otgb.physics.priors import Constant, Normal, Prior, Uniform

REFITTED = ((Constant, CONSTANT), (Uniform, UNIFORM), (Normal, NORMAL))  # the priors a recalibration refits


def family_of(given: Prior | None) -> str | None:
    """The family a recalibration refits ``given`` in, or None where it keeps it as given."""
    return next((family for kind, family in REFITTED if isinstance(given, kind)), None)


@dataclass(frozen=True)
class Recalibrated:
    """One parameter's refitted prior: its name, the config's prior and the fitted one (same family), and the 95 %
    intervals of its centre, (where it varies) its half-width or standard deviation, and (a uniform prior) its low
    and high bounds, each from the sandwich covariance (a bound's variance with the centre's and width's covariance);
    None where they could not be computed."""

    parameter: str
    before: Prior
    prior: Prior
    centre_interval: tuple[float, float] | None
    width_interval: tuple[float, float] | None
    bounds_intervals: tuple[tuple[float, float], tuple[float, float]] | None = None

    @property
    def moved(self) -> bool:
        """Whether the config's prior lies outside the fitted one's 95 % intervals (a bound of a uniform, the value of
        a constant, the mean or standard deviation of a normal); True where there are no intervals."""
        given = self.before
        if self.bounds_intervals is not None:
            return not all(low <= v <= high for v, (low, high) in zip((given.low, given.high), self.bounds_intervals))
        if self.centre_interval is None:
            return True
        outside = not self.centre_interval[0] <= centre(given) <= self.centre_interval[1]
        width = self.width_interval
        return outside or (width is not None and not width[0] <= spread(given) <= width[1])

    def text(self) -> str:
        """The fitted prior with its 95 % intervals, as the verdict says it."""
        if self.bounds_intervals is not None:
            (low_a, low_b), (high_a, high_b) = self.bounds_intervals
            return f"{prior_text(self.prior)} (95 %: low in [{low_a:.4g}, {low_b:.4g}], high in [{high_a:.4g}, {high_b:.4g}])"
        if self.centre_interval is not None:
            low, high = self.centre_interval
            return f"{prior_text(self.prior)} (95 % interval of its centre [{low:.4g}, {high:.4g}])"
        return f"{prior_text(self.prior)} (no interval: the fit is not at a minimum)"


@dataclass(frozen=True)
class Recalibration:
    """f_p with its refitted priors: each parameter's record, the recalibrated model, its validation scores and f_p
    alone's (with the same draws: common random numbers)."""

    parameters: list[Recalibrated]
    physics: PhysicsModel
    heldout: Scores
    f_p_heldout: Scores
    kept_as_given: list[str]  # parameters whose prior's kind is not refitted
    ended: Ended | None = field(default=None, repr=False, compare=False)  # where its fit ended, for refits

    @property
    def below_f_p(self) -> tuple[float, float]:
        """How far below f_p alone's its validation score lies, and that difference's standard error."""
        return difference(self.heldout, self.f_p_heldout)

    @property
    def part(self) -> str:
        """What its scores are on: the validation part, or the held-out folds where they are cross-fitted."""
        return heldout_part(self.heldout.folds > 1)

    @property
    def beats_f_p(self) -> bool:
        """Whether the recalibrated f_p fits the held-out part better than f_p alone by two standard errors."""
        return clears(*self.below_f_p)

    def answer_text(self) -> str:
        """The verdict's answer where this recalibration is it: each prior the data moved against the config's."""
        return f"f_p is complete, its parameters' priors are off: the recalibrated f_p, where {self.moved_text()},"

    def beside_text(self) -> str:
        """Where the answer is named terms on f_p with these priors: what follows the terms' names."""
        return f", on f_p with its parameters' priors recalibrated beside them ({self.moved_text()}),"

    def moved_text(self) -> str:
        """Each prior the data moved (:attr:`Recalibrated.moved`) against the config's, then those they did not."""
        moved = [r for r in self.parameters if r.moved]
        said = "; ".join(f"{r.parameter}'s prior should be {r.text()}, not {prior_text(r.before)}" for r in moved)
        kept = [r.parameter for r in self.parameters if not r.moved]
        agree = f"the priors of {', '.join(kept)} agree with the config's within their intervals" if kept else ""
        return "; ".join(part for part in (said, agree) if part)

    def unconfirmed(self) -> str:
        """Where the recalibration was tried and is not the answer: by how much it fits the held-out part better."""
        below, error = self.below_f_p
        return (
            f"f_p with its priors refitted ({', '.join(f'{r.parameter} {prior_text(r.prior)}' for r in self.parameters)}) fits "
            f"{self.part} no better than f_p alone by two standard errors ({below:+.3g} +- {error:.2g})"
        )

    def alike(self, terms: Scores) -> str | None:
        """Where this recalibration beats f_p alone, and f_p plus named terms (their validation ``terms`` scores) and
        it do not beat one another by two standard errors: the verdict's part that says so; else None."""
        gap, error = difference(terms, self.heldout)
        if not self.beats_f_p or clears(gap, error) or clears(-gap, error):
            return None
        priors = ", ".join(f"{r.parameter} {prior_text(r.prior)}" for r in self.parameters)
        return (
            f"{self.part} cannot tell these terms from f_p with recalibrated priors ({priors}; "
            f"{gap / error if error > 0 else 0:+.1f} standard errors): the model may lack physics, or its parameters' "
            "priors may be off"
        )


class ThetaPriors(torch.nn.Module):
    """Differentiable priors of theta: per parameter a centre moved in units of its size and (families that vary) a
    width scaled by the exponential of a parameter (it stays positive), started at the config's prior."""

    def __init__(self, priors: list[Prior]) -> None:
        super().__init__()
        self.families = [family_of(p) for p in priors]
        init = torch.tensor([centre(p) for p in priors], dtype=torch.float64)
        widths = torch.tensor([spread(p) if varies(f) else 1.0 for p, f in zip(priors, self.families)], dtype=torch.float64)
        self.register_buffer("init", init)
        self.register_buffer("scale", torch.where(init.abs() > 0, init.abs(), torch.ones_like(init)))
        self.register_buffer("init_width", widths)
        self.shift = torch.nn.Parameter(torch.zeros_like(init))
        self.log_width = torch.nn.Parameter(torch.zeros_like(init))  # width = init_width * exp(log_width)
        self.register_buffer("varying", torch.tensor([varies(f) for f in self.families]))

    @property
    def centre(self) -> Tensor:
        return self.init + self.scale * self.shift

    @property
    def width(self) -> Tensor:
        return torch.where(self.varying, self.init_width * torch.exp(self.log_width), torch.zeros_like(self.init))

    def draw(self, noise: Tensor) -> Tensor:
        """theta (n, k) for standard draws ``noise`` (n, k)."""
        return self.centre + self.width * noise

    def priors(self) -> list[Prior]:
        return [prior(f, c, w) for f, c, w in zip(self.families, self.centre.tolist(), self.width.tolist())]


def recalibrate(
    physics: PhysicsModel, train: Tensor, val: Tensor, steps: int, batch: int, seed: int, samples: int = 1,
    states: bool = False, folds: Folds | None = None, with_intervals: bool = True, ended: Ended | None = None,
) -> Recalibration | None:  # fmt: skip
    """f_p's theta priors (and, with ``states``, the priors of its initial state's components, for an ODE whose x0
    is drawn per component) refitted to ``train`` (module docstring) on ``samples`` simulated samples of ``batch``
    (one where no refitted prior varies), scored on ``val`` or, with ``folds``, cross-fitted over them
    (:mod:`otgb.discovery.crossfit`, each fold's refit from where this fit ended); without ``with_intervals``, none are
    computed (a refit whose scores alone count); from ``ended`` (a recalibration's end, of the same parameters), the fit
    starts there; None where no prior is of a kind it refits or the fit diverged."""
    own = getattr(physics, "base", physics).theta_names  # f_p's parameters, not an augmented model's coefficients
    components = physics.state_names if states and not isinstance(physics, FieldModel) else ()
    names = [n for n in (*own, *components) if family_of(physics.priors.get(n)) is not None]
    if not names:
        return None
    start = (ThetaPriors([physics.priors[n] for n in names]), Curvature()) if ended is None else ended.restart()
    theta_priors, curvature = start
    samples = samples if any(map(varies, theta_priors.families)) else 1
    sample = _sample(physics, names, theta_priors.families, train, batch * samples, seed, samples)
    if not _fit(physics, names, theta_priors, sample, steps, curvature):
        return None
    end = Ended(theta_priors, curvature)
    fitted = dict(zip(names, theta_priors.priors()))
    recalibrated = physics.with_priors(fitted)
    intervals = _intervals(physics, names, theta_priors, sample) if with_intervals else None
    records = [
        Recalibrated(n, physics.priors[n], fitted[n], *(intervals[i] if intervals else (None, None, None)))
        for i, n in enumerate(names)
    ]
    kept = [n for n in own if n not in names]
    if folds is None:
        scores = discrepancies(recalibrated, [], [], val, seed), discrepancies(physics, [], [], val, seed)
        return Recalibration(records, recalibrated, *scores, kept, end)

    def refitted(k: int, rest: Tensor, held_out: Tensor) -> Scores:  # the fit again on the other folds, from its end
        again, memory = end.restart()
        on_rest = _sample(physics, names, again.families, rest, batch * samples, seed, samples)
        if not _fit(physics, names, again, on_rest, refit_steps(steps), memory):
            return Scores.diverged(HELDOUT_REPEATS)
        return discrepancies(physics.with_priors(dict(zip(names, again.priors()))), [], [], held_out, seed)

    alone = cross_fitted(folds, lambda k, rest, held_out: discrepancies(physics, [], [], held_out, seed))
    return Recalibration(records, recalibrated, cross_fitted(folds, refitted), alone, kept, end)


@dataclass(frozen=True)
class _Sample:
    targets: Tensor
    x0: Tensor
    theta: Tensor  # the config's draws, whose columns of the refitted parameters are replaced
    noise: Tensor  # (n, k) standard draws of the refitted parameters
    samples: int = 1  # independent samples of equal size, one after the other
    signals: Tensor | None = None  # a driven model's input signals of each simulated trajectory


def _sample(
    physics: PhysicsModel, names: list[str], families: list[str], measured: Tensor, n: int, seed: int, samples: int
) -> _Sample:
    g = torch.Generator().manual_seed(seed)
    targets = measured[torch.randperm(len(measured), generator=g)[:n]].float()
    x0, theta = physics.sample_initial_state(n, g), physics.sample_theta(n, g)
    noise = torch.stack([standard_noise(f, (n,), g) for f in families], 1)
    return _Sample(targets, x0, theta, noise, samples, physics.sample_signals(n, g))


def _simulate(physics: PhysicsModel, names: list[str], sample: _Sample, theta_of_rows: Callable[[Tensor], Tensor]) -> Simulate:
    """The observed trajectories of rows of ``sample``, the refitted priors' columns of theta and of x0 from
    ``theta_of_rows(row indices)`` (one column per name, in ``names``' order)."""
    in_theta = [i for i, n in enumerate(names) if n in physics.theta_names]
    in_x0 = [i for i, n in enumerate(names) if n not in physics.theta_names]
    columns = [physics.theta_names.index(names[i]) for i in in_theta]
    components = [physics.state_names.index(names[i]) for i in in_x0]

    def simulate(rows: slice) -> Tensor:
        theta, x0 = sample.theta[rows].clone().double(), sample.x0[rows]
        index = torch.arange(len(sample.x0))[rows]
        values = theta_of_rows(index)
        theta[:, columns] = values[:, in_theta]
        if components:
            x0 = x0.clone().double()
            x0[:, components] = values[:, in_x0]
            x0 = x0.float()
        signals = None if sample.signals is None else sample.signals[rows]
        return physics.observe(physics.solve(physics.vector_field, x0, theta.float(), signals=signals))

    return simulate


def _fit(
    physics: PhysicsModel, names: list[str], theta_priors: ThetaPriors, sample: _Sample, steps: int, curvature: Curvature
) -> bool:
    """L-BFGS on the mean discrepancy of the samples (:func:`otgb.discovery.lbfgs.minimise`, from ``curvature`` and
    leaving its own there); whether it ended at finite priors."""
    simulate = _simulate(physics, names, sample, lambda index: theta_priors.draw(sample.noise[index].double()))

    def is_finite() -> bool:
        return bool(torch.isfinite(theta_priors.centre).all() and torch.isfinite(theta_priors.width).all())

    target = Target.of(sample.targets)
    minimise(list(theta_priors.parameters()), simulate, len(sample.x0), target, sample.samples, steps, is_finite, curvature)
    return is_finite()


Interval = tuple[float, float]


def _intervals(
    physics: PhysicsModel, names: list[str], theta_priors: ThetaPriors, sample: _Sample
) -> list[tuple[Interval, Interval | None, tuple[Interval, Interval] | None]] | None:
    """Per parameter the 95 % intervals of its centre, (where it varies) its width and (a uniform) its bounds
    c - w and c + w; None where the sandwich cannot be computed."""
    varying = theta_priors.varying.tolist()
    p = torch.cat([theta_priors.centre, theta_priors.width[theta_priors.varying]]).detach()
    k, n = len(names), len(sample.x0)
    sizes = torch.cat([theta_priors.scale, theta_priors.width[theta_priors.varying].detach().clamp_min(1e-12)])
    where_width = [i for i, v in enumerate(varying) if v]

    def simulator(variants: Tensor) -> Simulate:
        def theta_of_rows(index: Tensor) -> Tensor:
            variant, row = variants[index // n], index % n
            width = torch.zeros(len(index), k, dtype=variants.dtype)
            width[:, where_width] = variant[:, k:]
            return variant[:, :k] + width * sample.noise[row].double()

        repeat = lambda v: None if v is None else v.repeat(len(variants), *[1] * (v.dim() - 1))  # noqa: E731
        grid = _Sample(sample.targets, repeat(sample.x0), repeat(sample.theta), repeat(sample.noise), sample.samples,
                       repeat(sample.signals))  # fmt: skip
        simulate = _simulate(physics, names, grid, theta_of_rows)
        return lambda rows: simulate(rows).double()

    covariance = sandwich(p, STEP * sizes, simulator, sample.targets.double(), n, sample.samples)
    if covariance is None or isinstance(covariance, int):
        return None

    def interval(value: Tensor, variance: Tensor) -> Interval:
        error = float(variance.clamp_min(0).sqrt())
        return (float(value) - Z95 * error, float(value) + Z95 * error)

    C, records = covariance, []
    for i in range(k):
        centre_interval, width_interval, bounds = interval(p[i], C[i, i]), None, None
        if varying[i]:
            j = k + where_width.index(i)
            width_interval = interval(p[j], C[j, j])
            if theta_priors.families[i] == UNIFORM:  # low = c - w, high = c + w
                bounds = tuple(interval(p[i] + sign * p[j], C[i, i] + C[j, j] + 2 * sign * C[i, j]) for sign in (-1, 1))
        records.append((centre_interval, width_interval, bounds))
    return records
