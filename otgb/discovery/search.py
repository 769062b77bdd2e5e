"""Search: name an effect whose shape the grey-box's correction missed, from a fit of the whole local library.

The OT grey-box's correction f_phi can learn an effect's average over the visited states and
not its shape (reaction-diffusion: f_phi is the reaction's mean, a constant; see
docs/discovery.md), and its regression then names the wrong terms. The measurements still
determine the shape. When the physics augmented along f_phi's route still disagrees with the
measurements, this route:

1. fits every *local* candidate of the acting components together, by distribution matching
   (:func:`otgb.discovery.refine.fit`), from f_phi's least-squares coefficients. Local: a
   function of the state at one point (constants, monomials, sin/cos, v|v|, sign); spatial
   derivatives stay with f_phi's route, since free coefficients on them make the PDE ill-posed
   (a negative diffusion blows up) and the joint fit unstable. The columns are collinear along
   the visited states, so the coefficients are not identified, but the correction g they sum
   to is;
2. evaluates g along the fitted model's trajectories and finds, for each number of terms k, the
   subset whose least-squares fit of g leaves the smallest residual. Every subset is tried
   (from the Gram matrix of the unit-RMS columns): forward selection fails on collinear
   columns, where the best pair need not contain the best single term;
3. scores the ten best subsets of each size on the validation measurements with their
   least-squares coefficients (g's residual alone ranks near-collinear subsets by noise), fits
   the three best of them by distribution matching and scores them again; the subsets the best
   one does not beat are kept as the step's alternatives (``report.json``'s ``search``). f_p alone
   is size 0. Sizes grow until two in a row do not beat the leader (the last size that beat the
   leader before it) by two standard errors, as f_phi's route does (a size that lowers the
   held-out score by less than its noise does not keep the search going); the sparsest model that
   beats f_p alone and that the best does not beat, each by two standard errors
   (:func:`otgb.discovery.scores.beats`), is kept, and nothing when the best does not beat f_p
   alone: an effect outside the library is then not given the name of the library term that
   happens to fit the validation part's noise best;
4. drops from the kept model, one at a time, a term whose coefficient's 95 % interval (fitted on the
   training measurements, :mod:`otgb.discovery.intervals`) holds zero, the least certain first,
   refitting the rest, as long as what is left beats f_p alone. The subsets of step 3 were chosen
   on the validation part that then compares them, so a near-zero extra term can beat the sparser
   model by two standard errors by chance (on a pendulum with viscous friction the search kept a
   spring of coefficient -0.004, interval [-0.17, 0.165], beside the friction); the evidence step
   takes an added term under the same rule.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from math import comb
from typing import Any

import numpy as np
import torch
from torch import Tensor

from otgb.discovery.families import centre
from otgb.discovery.intervals import fitted_intervals
from otgb.discovery.library import Candidate
from otgb.discovery.refine import FittedTerms, Fitting
from otgb.discovery.regression import design_matrix
from otgb.discovery.scores import Scores, beats, difference, discrepancies
from otgb.discovery.seeds import FITTED_CORRECTION, stream
from otgb.physics.base import PhysicsModel
from otgb.physics.features import is_local
from otgb.physics.priors import Constant

MAX_SUBSETS = 200_000  # subsets of one size enumerated at most (compute bound; the held-out check picks the size)
TRAJECTORIES = 64  # fitted-model trajectories along which g is evaluated
PROPOSALS = 10  # subsets of each size (the best by g's residual) scored on held-out data before one is fitted
PROXY_REPEATS = 3  # simulation draws of that score
REFITS = 3  # of those, the best by that score fitted by distribution matching


@dataclass
class SearchStep:
    """One size of the search: the subset fitted best by distribution matching, and those it does not beat."""

    candidates: list[Candidate]
    g_residual: float  # relative RMS residual of the subset's least-squares fit of g
    fitted: FittedTerms
    alternatives: list[list[Candidate]] = field(default_factory=list)  # subsets of this size it does not beat
    versus_f_p: tuple[float, float] = (float("nan"), float("nan"))  # f_p alone's held-out score minus its, standard error


@dataclass
class Unsupported:
    """A term step 4 dropped from the search's model: its coefficient and that coefficient's 95 % interval."""

    candidate: Candidate
    coefficient: float
    interval: tuple[float, float]


@torch.no_grad()
def fitted_correction(
    physics: PhysicsModel, dense: FittedTerms, n: int, seed: int
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:  # fmt: skip
    """States (n, T, *state), theta, the fitted terms' correction (n, T, *state) along n trajectories of the fitted model,
    and a driven model's input values along them (n, T, I; None: not driven)."""
    model = dense.model(physics)
    g = stream(seed, FITTED_CORRECTION)
    x0, theta, signals = physics.sample_initial_state(n, g), physics.sample_theta(n, g), physics.sample_signals(n, g)
    coefficients = torch.tensor([centre(p) for p in dense.priors]).expand(n, -1)
    states = model.solve(model.vector_field, x0, torch.cat([theta, coefficients], 1), signals=signals)
    steps = states.shape[1]
    flat, theta_rows = states.flatten(0, 1), theta.repeat_interleave(steps, 0)
    inputs = None if signals is None else physics.inputs_along(signals)
    flat_inputs = None if inputs is None else inputs.flatten(0, 1)
    with_terms = model.vector_field(flat, torch.cat([theta_rows, coefficients[:1].expand(len(flat), -1)], 1), inputs=flat_inputs)
    correction = (with_terms - physics.vector_field(flat, theta_rows, inputs=flat_inputs)).reshape(states.shape)
    return states, theta, correction, inputs


def stacked_design(
    physics: PhysicsModel, candidates: list[Candidate], states: Tensor, theta: Tensor, correction: Tensor, seed: int,
    inputs: Tensor | None = None,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Rows of every acting component stacked: a candidate's column is zero on the other components' rows."""
    blocks, targets = [], []
    for component in dict.fromkeys(c.component for c in candidates):
        index = physics.state_names.index(component)
        design = design_matrix(physics, candidates, states, theta, correction[:, :, index], seed, inputs)
        mask = np.array([c.component == component for c in candidates], dtype=float)
        blocks.append(design.X * mask)
        targets.append(design.y)
    return np.concatenate(blocks), np.concatenate(targets)


def best_subsets(X: np.ndarray, y: np.ndarray, size: int, keep: int = 1) -> list[tuple[list[int], float]] | None:
    """The ``keep`` subsets of ``size`` columns whose least-squares fits of y leave the smallest residuals, best
    first, each with its relative RMS residual; None when there are more subsets than ``MAX_SUBSETS``."""
    usable = np.flatnonzero(np.sqrt((X**2).mean(0)) > 0)
    if size > len(usable) or comb(len(usable), size) > MAX_SUBSETS:
        return None
    Xs = X[:, usable] / np.sqrt((X[:, usable] ** 2).mean(0))
    gram, moments, total = Xs.T @ Xs, Xs.T @ y, float(y @ y)
    subsets = np.array(list(combinations(range(len(usable)), size)))
    grams = gram[subsets[:, :, None], subsets[:, None, :]] + 1e-12 * np.eye(size) * len(y)
    solutions = np.linalg.solve(grams, moments[subsets][..., None])[..., 0]
    residual = np.sqrt(np.clip(total - (moments[subsets] * solutions).sum(1), 0.0, None) / max(total, 1e-300))
    order = np.argsort(residual, kind="stable")[:keep]
    return [([int(usable[j]) for j in subsets[i]], float(residual[i])) for i in order]


def subset_values(X: np.ndarray, y: np.ndarray, subset: list[int]) -> list[float]:
    return list(np.linalg.lstsq(X[:, subset], y, rcond=None)[0])


def _proxy(physics: PhysicsModel, terms: list[Candidate], values: list[float], heldout: Tensor, seed: int) -> float:
    """A proposal's held-out discrepancy with its least-squares coefficients on g, before any fit (cheap: no gradients)."""
    return discrepancies(physics, terms, [Constant(float(v)) for v in values], heldout, seed, PROXY_REPEATS).mean


def _best_of_size(
    physics: PhysicsModel,
    local: list[Candidate],
    X: np.ndarray,
    y: np.ndarray,
    size: int,
    heldout: Tensor,
    seed: int,
    fitted: Fitting,
) -> SearchStep | None:
    """Step 3 for one size: proposals by g's residual, ranked by their held-out score, the best few fitted."""
    ranked = best_subsets(X, y, size, PROPOSALS)
    if ranked is None:
        return None
    proposals = [([local[j] for j in subset], residual, subset_values(X, y, subset)) for subset, residual in ranked]
    proposals.sort(key=lambda p: _proxy(physics, p[0], p[2], heldout, seed))
    steps = [SearchStep(terms, residual, fitted(terms, start)) for terms, residual, start in proposals[:REFITS]]
    step = min(steps, key=lambda s: s.fitted.heldout_energy)
    step.alternatives = [s.candidates for s in steps if s is not step and not beats(step.fitted.heldout, s.fitted.heldout)]
    return step


def search(
    candidates: list[Candidate], init: list[float], fitting: Fitting, report: Any = print
) -> tuple[FittedTerms | None, list[SearchStep], list[Unsupported]]:
    """Steps 1-4 of the module docstring on ``candidates`` (started at ``init``), each fit made by ``fitting``: the
    model kept, the path and the terms step 4 dropped."""
    physics, seed = fitting.physics, fitting.seed
    pairs = [(c, v) for c, v in zip(candidates, init) if is_local(c.feature, physics)]
    if not pairs:
        return None, [], []
    local, values = [c for c, _ in pairs], [v for _, v in pairs]
    dense = fitting(local, values)
    report(f"search: {len(local)} local candidates fitted together, held-out energy {dense.heldout_energy:.4g}")
    if not dense.heldout.finite:
        return None, [], []
    states, theta, correction, inputs = fitted_correction(physics, dense, TRAJECTORIES, seed)
    X, y = stacked_design(physics, local, states, theta, correction, seed, inputs)
    alone = fitting.alone()  # f_p itself, size 0
    report(f"search: f_p alone, held-out energy {alone.mean:.4g}")
    path: list[SearchStep] = []
    scores, leader = [alone], 0  # held-out scores by size; the last size that beat the leader before it
    for size in range(1, len(local) + 1):
        step = _best_of_size(physics, local, X, y, size, fitting.val, seed, fitting)
        if step is None:
            break
        step.versus_f_p = difference(step.fitted.heldout, alone)
        path.append(step)
        scores.append(step.fitted.heldout)
        names = [f"{c.feature} on d{c.component}/dt" for c in step.candidates]
        report(f"search: {size} term(s) {names}: held-out energy {step.fitted.heldout_energy:.4g}")
        if beats(scores[size], scores[leader]):
            leader = size
        elif size - leader >= 2:
            break
    kept, dropped = supported(sparsest_kept([s.fitted for s in path], alone), alone, fitting, report)
    return kept, path, dropped


def sparsest_kept(fitted: list[FittedTerms], alone: Scores) -> FittedTerms | None:
    """Of the search's models (sparsest first), the sparsest that beats f_p alone (``alone``) and that the best does
    not beat, each by two standard errors; None when none is fitted, all diverged, or the best does not beat f_p."""
    best = min(fitted, key=lambda f: f.heldout_energy, default=None)
    if best is None or not beats(best.heldout, alone):
        return None
    return next(f for f in fitted if beats(f.heldout, alone) and not beats(best.heldout, f.heldout))


def supported(
    kept: FittedTerms | None, alone: Scores, fitting: Fitting, report: Any = print
) -> tuple[FittedTerms | None, list[Unsupported]]:
    """Step 4: ``kept`` without the terms whose 95 % interval holds zero (the least certain dropped first, the rest
    refitted from their values), and the dropped terms; None where what is left does not beat f_p alone (``alone``).
    A model whose intervals cannot be computed (not at a minimum) is kept as it is."""
    dropped: list[Unsupported] = []
    while kept is not None:
        intervals = fitted_intervals(fitting, kept)
        if intervals is None:
            report("search: the kept model's intervals cannot be computed (not at a minimum): its terms are kept as they are")
            return kept, dropped
        holding = [(certainty(low, high), k) for k, (low, high) in enumerate(intervals.centre) if low <= 0 <= high]
        if not holding:
            return kept, dropped
        k = min(holding)[1]
        term = Unsupported(kept.candidates[k], centre(kept.priors[k]), intervals.centre[k])
        dropped.append(term)
        (low, high), on = term.interval, f"{term.candidate.feature} on d{term.candidate.component}/dt"
        report(f"search: dropped {on}: its coefficient's 95 % interval [{low:.3g}, {high:.3g}] holds zero")
        kept = _without(kept, k, fitting)
        if kept is not None and not beats(kept.heldout, alone):
            report("search: without it, the model no longer beats f_p alone by two standard errors")
            kept = None
    return None, dropped


def _without(fitted: FittedTerms, k: int, fitting: Fitting) -> FittedTerms | None:
    """``fitted`` refitted without its term ``k``, the rest started at their values; None when no term is left."""
    rest = [i for i in range(len(fitted.candidates)) if i != k]
    if not rest:
        return None
    return fitting([fitted.candidates[i] for i in rest], [centre(fitted.priors[i]) for i in rest], natural_scales=False)


def certainty(low: float, high: float) -> float:
    """How far an interval's midpoint sits from zero, in half-widths (the estimate's |z| / 1.96)."""
    return abs(low + high) / max(high - low, 1e-300)
