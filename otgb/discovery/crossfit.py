"""Held-out evidence from every measured trajectory: scores cross-fitted over K folds of the training and validation
parts.

With ``discover.folds`` = K > 1, the measured training and validation trajectories are pooled and split into K folds
at random, once per run (the same folds for every model, so that two models' scores are paired). A fitted model's
held-out score is then made K times: the same fit (its prior family and scales) made again on the other K - 1 folds,
and scored on the fold left out, with the simulation draws that every model's score of that fold shares (common random
numbers, :func:`otgb.discovery.scores.discrepancies`). The K scores combine into one
:class:`~otgb.discovery.scores.Scores`: per simulation draw, the folds' discrepancies weighted by their sizes; per
measured trajectory, its row from the fold that held it out. Every measured trajectory of the two parts is so seen out
of sample by each decision, not only the validation part's.

A fold's refit starts where the fit on the training part ended and takes :func:`refit_steps` of its L-BFGS
iterations (a fifth): the other K - 1 folds share most of their trajectories with the training part, so the two optima
lie within sampling noise of each other, and a few coefficients' smooth fixed-sample discrepancy is minimised from
there in a few iterations. The refit must end at the other folds' own optimum, not stay near its start (which saw most
of the fold, and would favour the model with more coefficients); ``tests/test_crossfit.py`` measures that it does.

The standard error of a difference of two such scores (:func:`otgb.discovery.scores.difference`) adds the simulation
draws' part and the measured sample's; the K folds' fits share most of their training data, so their held-out errors
are correlated, and the measured part's variance is scaled by Nadeau and Bengio's correction (2003),
:func:`~otgb.discovery.scores.fold_inflation`: 1 + K/(K-1), 2.25 at K = 5.

What stays on one part: the answer's own coefficients are fitted on the training part (its intervals, and the checks
of the disagreement map on the validation part, see data no fit of that answer saw), the grey-box is trained once on
the training part (its undertrained check scores it on the validation part), and the test part is the final
verification's alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from otgb.discovery.scores import Scores
from otgb.errors import InputError

REFIT_SHARE = 5  # a fold's refit takes one in this many of the iterations of the fit on the training part


def refit_steps(steps: int) -> int:
    """L-BFGS iterations of a fold's refit that starts where a fit of ``steps`` iterations ended (module docstring)."""
    return max(1, math.ceil(steps / REFIT_SHARE))


def heldout_part(cross_fitted: bool) -> str:
    """What the held-out scores of a run's decisions are on, in the words of its log and verdict."""
    return "the held-out folds" if cross_fitted else "the validation part"


@dataclass(frozen=True)
class Folds:
    """The pooled training and validation trajectories (n, T, *obs) and each fold's rows in that pool."""

    pool: Tensor
    index: tuple[Tensor, ...]

    @classmethod
    def of(cls, train: Tensor, val: Tensor, k: int, seed: int) -> Folds | None:
        """K folds of ``train`` and ``val`` pooled, drawn with ``seed``; None for K = 1 (one held-out part)."""
        if k <= 1:
            return None
        pool = torch.cat([train, val])
        if len(pool) < 2 * k:
            raise InputError(
                f"discover.folds={k}: the {len(pool)} measured training and validation trajectories cannot be split into "
                f"{k} folds of at least 2; expected fewer folds"
            )
        order = torch.randperm(len(pool), generator=torch.Generator().manual_seed(seed))
        return cls(pool, tuple(order.tensor_split(k)))

    @property
    def k(self) -> int:
        return len(self.index)

    def split(self, fold: int) -> tuple[Tensor, Tensor]:
        """The other folds' trajectories (to fit on) and fold ``fold``'s (to score on)."""
        rest = torch.cat([self.index[j] for j in range(self.k) if j != fold])
        return self.pool[rest], self.pool[self.index[fold]]


def cross_fitted(folds: Folds, score_fold: Callable[[int, Tensor, Tensor], Scores]) -> Scores:
    """The cross-fitted :class:`Scores` of a fitting procedure: ``score_fold(k, rest, held_out)`` refits on ``rest`` (the
    folds but k) and scores on ``held_out`` (fold k), for each fold; combined as the module docstring says (diverged if
    any fold's model diverged)."""
    per_fold = [score_fold(k, *folds.split(k)) for k in range(folds.k)]
    if not all(s.finite for s in per_fold):
        return Scores.diverged(max(len(s.draws) for s in per_fold), folds.k)
    sizes = torch.tensor([float(len(i)) for i in folds.index], dtype=torch.float64)
    weights = sizes / sizes.sum()
    draws = (torch.tensor([s.draws for s in per_fold], dtype=torch.float64) * weights[:, None]).sum(0)
    return Scores(draws.tolist(), torch.cat([s.rows for s in per_fold]), folds.k)
