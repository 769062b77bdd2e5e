"""Joint samples (theta, x0, y) and the base of the two-sample metrics.

The paper ("Hybrid Generative Modeling for Incomplete Physics: Deep Grey-Box Meets Optimal
Transport", ICLR 2025) evaluates on the joint distribution pi(theta, x0, y): a model is only
right if each generated y fits its own inputs, so every sample row holds the inputs next to
the trajectory.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from otgb.data.gaps import filled


def joint_samples(theta: Tensor, x0: Tensor, y: Tensor) -> Tensor:
    """Rows (theta_i, x0_i, y_ij) for every input i and draw j.

    theta (N, P), x0 (N, *state), y (N, M, T, *obs) -> (N * M, P + |state| + T * |obs|).
    """
    if len(x0) != len(theta):
        raise ValueError(f"joint samples need theta (N, P) and x0 (N, ...), same N; got {tuple(theta.shape)}, {tuple(x0.shape)}")
    return sample_rows(torch.cat([theta.flatten(1), x0.flatten(1).to(theta.dtype)], dim=1), y)


def sample_rows(cond: Tensor, y: Tensor) -> Tensor:
    """Rows (cond_i, y_ij) for every input i and draw j: cond (N, C) (C may be 0), y (N, M, T, *obs) -> (N * M, C + T * |obs|)."""
    if y.dim() < 3 or cond.dim() != 2 or len(cond) != len(y):
        raise ValueError(f"sample rows need cond (N, C) and y (N, M, T, ...); got {tuple(cond.shape)}, {tuple(y.shape)}")
    n, m = y.shape[:2]
    return torch.cat([cond.to(y.dtype).repeat_interleave(m, dim=0), y.reshape(n * m, -1)], dim=1)


class TwoSampleMetric(Metric):
    """Accumulates two samples p and q (rows of features) over batches and processes.

    ``update(p, q)`` appends rows (p is the reference sample, e.g. the measured/DGP draws;
    q the candidate, e.g. the model's); ``compute`` scores the whole samples with
    :meth:`score`, which subclasses define and which returns named scalars. A NaN is a
    missing value, at like places in both samples (:mod:`otgb.data.gaps`): a score of whole
    rows sees it as 0, one that sets ``reads_missing`` reads it itself.
    """

    full_state_update = False
    reads_missing = False  # whether score reads missing values (NaN) itself; else it gets them as 0

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.add_state("p", default=[], dist_reduce_fx="cat")
        self.add_state("q", default=[], dist_reduce_fx="cat")
        self.across_halves = (0, 0)  # (repeats, seed): score across halves (:func:`across_halves`); 0 repeats: whole

    def update(self, p: Tensor, q: Tensor) -> None:
        if p.dim() != 2 or q.dim() != 2 or p.shape[1] != q.shape[1]:
            raise ValueError(f"{type(self).__name__}.update: expected (n, D) and (m, D), got {tuple(p.shape)}, {tuple(q.shape)}")
        for name, rows in (("p", p), ("q", q)):
            if bool(torch.isinf(rows).any()):
                raise ValueError(f"{type(self).__name__}.update: sample {name} contains Inf (NaN: a missing value)")
        self.p.append(p.detach())
        self.q.append(q.detach())

    def compute(self) -> dict[str, Tensor]:
        p, q = dim_zero_cat(self.p), dim_zero_cat(self.q)
        if not self.reads_missing:  # a missing value (NaN, on both samples at like places: otgb.data.gaps) is 0
            p, q = filled(p), filled(q)
        repeats, seed = self.across_halves
        return across_halves(self.score, p, q, repeats, seed) if repeats else self.score(p, q)

    def score(self, p: Tensor, q: Tensor) -> dict[str, Tensor]:
        raise NotImplementedError


def across_halves(
    score: Callable[[Tensor, Tensor], dict[str, Tensor]], p: Tensor, q: Tensor, repeats: int, seed: int
) -> dict[str, Tensor]:
    """``score`` of one random half of the inputs' measured rows ``p`` against the candidate's rows ``q`` of the other
    half; mean and ``_std`` over ``repeats`` splits.

    For a candidate drawn on the very inputs of the measured rows (a file that recorded each trajectory's
    inputs): row i of ``p`` (one per input) and rows i*m ... i*m + m - 1 of ``q`` (m draws per input) share
    input i, so the two samples are not independent, and a two-sample statistic of the whole samples is
    biased towards "alike" (a C2ST far below 0.5, an unbiased MMD or energy distance below its noise
    floor: each draw sits next to its own measurement). Across halves no draw meets its own measurement.
    The splits are the marginal Reference's (:func:`random_halves`, which
    :func:`otgb.metrics.joint.split_half_scores` draws too), which scores the two halves of the measurements
    against each other: the candidate is scored as the Reference is, with its draws in place of one half.
    """
    n = len(p)
    if n < 2 or len(q) % n:
        raise ValueError(f"across halves needs one measured row per input and m draws each: got {n} and {len(q)} rows")
    draws = q.reshape(n, len(q) // n, q.shape[1])
    runs = []
    for measured, drawn in random_halves(n, repeats, seed):
        measured, drawn = measured.to(p.device), drawn.to(p.device)
        runs.append(score(p[measured], draws[drawn].reshape(-1, q.shape[1])))
    return mean_and_std(runs)


def random_halves(n: int, repeats: int, seed: int) -> list[tuple[Tensor, Tensor]]:
    """``repeats`` random splits of the indices 0 .. n-1 into two halves of n // 2 (one left out when n is odd),
    drawn from ``seed``: the marginal Reference's splits, and the same ones for whatever is scored beside it."""
    g = torch.Generator().manual_seed(seed)
    orders = [torch.randperm(n, generator=g) for _ in range(repeats)]
    return [(order[: n // 2], order[n // 2 : 2 * (n // 2)]) for order in orders]


def mean_and_std(runs: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    """Mean (``<name>``) and std (``<name>_std``) over repeated evaluations, elementwise for vectors."""
    results = {}
    for name in runs[0]:
        if name.endswith("_std"):
            continue
        values = torch.stack([r[name] for r in runs])
        results[name] = values.mean(0)
        results[f"{name}_std"] = values.std(0) if len(runs) > 1 else torch.zeros_like(values[0])
    return results
