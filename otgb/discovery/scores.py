"""Held-out scores of a model and the one rule that compares two: a model beats another where its discrepancy is
lower by more than two standard errors of the difference (simulation draws with common random numbers plus the
finite measured sample)."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from otgb.discovery.discrepancy import Target, discrepancy_and_rows
from otgb.discovery.library import Candidate
from otgb.discovery.log import diverged
from otgb.discovery.seeds import FIT_INPUTS, FIT_NOISE, stream
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel
from otgb.physics.priors import Constant, Prior
from otgb.physics.terms import LibraryTerm

CPU = torch.device("cpu")
HELDOUT_REPEATS = 10  # simulation draws per held-out score


@dataclass
class Scores:
    """A model's discrepancy (:func:`otgb.discovery.discrepancy.discrepancy`) to a measured set: one value per
    simulation draw (``draws``), and per measured trajectory its cross term averaged over the draws (``rows``: twice its
    mean distance to the simulated trajectories, summed over the discrepancy's parts).

    Two models scored against the same measured set differ by the mean of their ``rows``
    differences (the measured set's own within-sample term cancels) and by their simulated
    samples; the first is how the measured sample's own randomness enters a comparison.
    """

    draws: list[float]
    rows: Tensor = field(default_factory=lambda: torch.zeros(0))
    folds: int = 1  # cross-fitted over this many folds (:mod:`otgb.discovery.crossfit`); 1: scored on one held-out part

    @property
    def mean(self) -> float:
        return float(torch.tensor(self.draws).mean())

    @property
    def finite(self) -> bool:
        return bool(torch.isfinite(torch.tensor(self.draws)).all())

    @classmethod
    def diverged(cls, repeats: int, folds: int = 1) -> Scores:
        """The scores of a model that diverges for some inputs: it does not describe the data."""
        return cls([float("inf")] * repeats, folds=folds)


def simulate_finite(
    model: Augmented, x0: Tensor, theta: Tensor, signals: Tensor | None = None
) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Observed trajectories (n', T, *obs) of the augmented model [driven by ``signals``] without those that diverged
    (a coefficient that makes the model blow up, e.g. a growing cubic), and which of the n inputs diverged (n,)."""
    trajectories = model.observe(model.solve(model.vector_field, x0, theta, signals=signals))
    finite = torch.isfinite(trajectories.flatten(1)).all(1)
    return trajectories[finite], ~finite


def term_names(candidates: list[Candidate]) -> list[str]:
    return [f"{c.feature} on d{c.component}/dt" for c in candidates]


def on_device(physics: PhysicsModel, device: torch.device) -> PhysicsModel:
    """``physics`` itself on the CPU; elsewhere a copy moved to ``device`` (moving a module moves it in place, and the rest
    of discovery uses it on the CPU), in its current state (the measurement noise in force)."""
    return physics if device.type == "cpu" else copy.deepcopy(physics).to(device)


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
    inputs, noise = stream(seed, FIT_INPUTS), stream(seed, FIT_NOISE)
    n, values, rows = len(measured), [], torch.zeros(len(measured), dtype=torch.float64, device=device)
    target = Target.of(measured.double().to(device))
    for _ in range(repeats):
        x0, theta, signals = base.sample_initial_state(n, inputs), base.sample_theta(n, inputs), base.sample_signals(n, inputs)
        coefficients = (
            torch.stack([p.quantile(torch.rand(n, generator=noise)) for p in priors], 1) if priors else torch.zeros(n, 0)
        )
        signals = None if signals is None else signals.to(device)
        theta_rows = torch.cat([theta, coefficients.float()], dim=1).to(device)
        simulated, bad = simulate_finite(model, x0.to(device), theta_rows, signals)
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
    Cross-fitted scores (``folds`` > 1) scale the second by :func:`fold_inflation`: their
    folds' fits share most of their training data. A model that diverged is infinitely worse.
    """
    if a.folds != b.folds:
        raise ValueError(f"scores of {a.folds} and {b.folds} folds are not comparable")
    if not (a.finite and b.finite):
        return (float("inf") if a.finite else float("-inf") if b.finite else float("nan")), float("nan")
    differences = torch.tensor(b.draws) - torch.tensor(a.draws)
    variance = differences.var() / len(differences)
    if len(a.rows) > 1 and len(a.rows) == len(b.rows):
        variance = variance + fold_inflation(a.folds) * (b.rows - a.rows).var() / len(a.rows)
    return float(differences.mean()), float(variance) ** 0.5


def fold_inflation(folds: int) -> float:
    """The factor on the measured sample's variance of a difference of scores cross-fitted over ``folds`` folds
    (Nadeau and Bengio, 2003, "Inference for the generalization error": (1/K + n_test/n_train) for K splits, times the
    K folds' n_test = n/K; 1 + K/(K-1)); 1 for scores on one held-out part."""
    return 1.0 if folds <= 1 else 1.0 + folds / (folds - 1)


def beats(a: Scores, b: Scores) -> bool:
    """Whether model a's discrepancy is lower than b's by more than two standard errors of the difference
    (:func:`difference`)."""
    gap, error = difference(a, b)
    if not math.isfinite(gap):
        return gap == float("inf")
    resolution = 1e-9 * abs(b.mean)  # below float rounding: a tie, e.g. a term fitted to zero
    return clears(gap, error, resolution)


STANDARD_ERRORS = 2  # how many standard errors of a difference decide between two models, everywhere in discovery


def clears(difference: float, standard_error: float, resolution: float = 0.0) -> bool:
    """Whether ``difference`` exceeds :data:`STANDARD_ERRORS` standard errors (and ``resolution``, a tie below float
    rounding): the one rule every choice between two models follows."""
    return difference > STANDARD_ERRORS * standard_error + resolution
