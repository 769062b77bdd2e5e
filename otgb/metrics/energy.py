"""Energy distance between two samples (Szekely & Rizzo, "Energy statistics: A class of
statistics based on distances", 2013), over the whole rows and per time step.

    E(P, Q) = 2 E||X - Y|| - E||X - X'|| - E||Y - Y'||   (>= 0, = 0 iff P = Q)

estimated without bias (the U-statistic: the within-sample means skip i = j), so it is 0 on
average for equal distributions whatever the sample sizes, and a Reference computed on two
halves of a set is on the same scale as a comparison of the whole set (the V-statistic, e.g.
GeomLoss's ``SamplesLoss("energy")``, which is half of it, grows like 1/n for equal
distributions; hence the few lines here). It is the MMD of the distance kernel, needs no
bandwidth, and is smooth in the samples, so it is a stable selection metric.

- :func:`energy_distance`: on pooled-standardised rows (as the MMD, :mod:`otgb.metrics.mmd`),
  so inputs and trajectory features of different units weigh alike.
- :func:`energy_per_time`: on the trajectory part of the rows, one distance per time step and
  observed component (per frame and channel for fields, over the spatial cells), in the
  observation's own units: where in time, and in which variable, two samples disagree.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from otgb.metrics.mmd import _as_float, standardise
from otgb.metrics.samples import TwoSampleMetric

MAX_BLOCK_ENTRIES = 2**25  # distance-matrix entries per batched call (256 MiB in float64)


def batched_energy(p: Tensor, q: Tensor, paired: bool = False) -> Tensor:
    """Unbiased energy distance of each batch entry: p (G, n, F), q (G, m, F) -> (G,), in bounded memory.

    ``paired``: row i of p and row i of q are dependent (the same inputs), so the cross mean
    skips i = j as the within-sample means do; otherwise a near-perfect paired sample would
    score below zero by about 2 E||X - X'|| / n. One feature (F = 1: a pendulum's angle at one
    time step) is computed by sorting (:func:`pair_distance_sums`), in O(n log n) instead of n^2.
    """
    n, m = p.shape[1], q.shape[1]
    if n < 2 or m < 2 or (paired and n != m):
        raise ValueError(f"the energy distance needs at least 2 points per sample (equally many if paired), got {n} and {m}")
    if p.shape[2] == 1:
        return _sorted_energy(p[..., 0], q[..., 0], paired)
    step = max(1, MAX_BLOCK_ENTRIES // (n * m + n * n + m * m))
    parts = []
    for g in range(0, len(p), step):
        a, b = p[g : g + step], q[g : g + step]
        within_a = torch.cdist(a, a).sum((1, 2)) / (n * (n - 1))  # the zero diagonal is skipped by the divisor
        within_b = torch.cdist(b, b).sum((1, 2)) / (m * (m - 1))
        cross = torch.cdist(a, b)
        cross = (cross.sum((1, 2)) - cross.diagonal(dim1=1, dim2=2).sum(1)) / (n * (n - 1)) if paired else cross.mean((1, 2))
        parts.append(2 * cross - within_a - within_b)
    return torch.cat(parts)


def pair_distance_sums(x: Tensor) -> Tensor:
    """Sum over pairs i < j of |x_i - x_j| along the last axis (..., n) -> (...): with x sorted, each x_(k) is
    the larger of k - 1 pairs and the smaller of n - k, so the sum is sum_k x_(k) (2k - n - 1)."""
    n = x.shape[-1]
    weights = 2 * torch.arange(1, n + 1, dtype=x.dtype, device=x.device) - n - 1
    return (x.sort(-1).values * weights).sum(-1)


def row_distance_sums(a: Tensor, b: Tensor) -> Tensor:
    """sum_i |a_i - b_j| for every b_j: a (..., n), b (..., m) -> (..., m), by sorting a (no n x m matrix)."""
    ordered = a.sort(-1).values.contiguous()
    cumulative = torch.nn.functional.pad(ordered.cumsum(-1), (1, 0))
    below = torch.searchsorted(ordered, b.contiguous())  # how many a_i lie below b_j
    below_sum = cumulative.gather(-1, below)
    above_sum = cumulative[..., -1:] - below_sum
    return b * below - below_sum + above_sum - b * (a.shape[-1] - below)


def _sorted_energy(a: Tensor, b: Tensor, paired: bool) -> Tensor:
    """:func:`batched_energy` of one feature, a (G, n), b (G, m), in float64 about the pooled mean (the weighted
    sums of :func:`pair_distance_sums` cancel large terms)."""
    dtype = a.dtype
    a, b = a.double(), b.double()
    shift = torch.cat([a, b], -1).mean(-1, keepdim=True)
    a, b = a - shift, b - shift
    n, m = a.shape[-1], b.shape[-1]
    within_a, within_b = pair_distance_sums(a), pair_distance_sums(b)
    cross = pair_distance_sums(torch.cat([a, b], -1)) - within_a - within_b  # the pooled pairs less the within pairs
    cross = (cross - (a - b).abs().sum(-1)) / (n * (n - 1)) if paired else cross / (n * m)
    return (2 * cross - 2 * within_a / (n * (n - 1)) - 2 * within_b / (m * (m - 1))).to(dtype)


def energy_distance(p: Tensor, q: Tensor, paired: bool = False) -> Tensor:
    """Unbiased energy distance between the rows of p (n, D) and q (m, D), on pooled-standardised features."""
    p, q = standardise(*_as_float(p, q))
    return batched_energy(p[None].double(), q[None].double(), paired)[0]


def energy_per_time(p: Tensor, q: Tensor, trajectory_shape: tuple[int, ...], paired: bool = False) -> Tensor:
    """Energy distance per time step and component: (T, C) for trajectories (T, C, *space).

    p (n, D) and q (m, D) are rows whose last prod(trajectory_shape) features are a trajectory
    (T, C, *space) (leading features, the conditioning inputs, are ignored). Each (t, c) cell
    compares the two samples' values at that step and component (a vector over space for
    fields), in the observation's units.
    """
    p, q = _as_float(p, q)
    width = math.prod(trajectory_shape)
    if p.shape[1] < width:
        raise ValueError(f"energy_per_time: rows of {p.shape[1]} features hold no trajectory of shape {trajectory_shape}")
    steps, channels = trajectory_shape[0], trajectory_shape[1] if len(trajectory_shape) > 1 else 1

    def cells(rows: Tensor) -> Tensor:  # (n, width) -> (T * C, n, space)
        return rows[:, -width:].reshape(len(rows), steps * channels, -1).transpose(0, 1).double()

    return batched_energy(cells(p), cells(q), paired).reshape(steps, channels).float()


class EnergyDistance(TwoSampleMetric):
    """Energy distance on accumulated samples: ``{"energy"}``, and ``{"energy_per_time": (T, C)}`` when
    ``trajectory_shape`` (T, *obs) says where the trajectory sits in each row; ``paired``: see
    :func:`batched_energy`."""

    def __init__(self, trajectory_shape: tuple[int, ...] | None = None, paired: bool = False, **kwargs) -> None:
        super().__init__(**kwargs)
        self.trajectory_shape = None if trajectory_shape is None else tuple(trajectory_shape)
        self.paired = paired

    def score(self, p: Tensor, q: Tensor) -> dict[str, Tensor]:
        results = {"energy": energy_distance(p, q, self.paired).float()}
        if self.trajectory_shape is not None:
            results["energy_per_time"] = energy_per_time(p, q, self.trajectory_shape, self.paired)
        return results
