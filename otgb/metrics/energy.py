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
  observation's own units: where in time, and in which variable, two samples disagree. Where
  values are missing (NaN), each step's distance is over the rows measured there (NaN where
  a sample has fewer than 2), the whole rows' with a missing value as 0 on both samples.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable

import torch
from torch import Tensor

from otgb.compiling import EagerFallback, compile_generic
from otgb.data.gaps import filled
from otgb.metrics.mmd import _as_float, standardise
from otgb.metrics.samples import TwoSampleMetric

MAX_BLOCK_ENTRIES = 2**25  # distance-matrix entries per batched call (256 MiB in float64)
COMPILED_ENTRIES = 2**24  # distance-matrix entries of a call on the CPU from which it runs compiled (:func:`_distances`)

log = logging.getLogger("otgb.metrics")
_not_compilable: set[Callable] = set()


def batched_energy(p: Tensor, q: Tensor, paired: bool = False) -> Tensor:
    """Unbiased energy distance of each batch entry: p (G, n, F), q (G, m, F) -> (G,), in bounded memory.

    ``paired``: row i of p and row i of q are dependent (the same inputs), so the cross mean
    skips i = j as the within-sample means do; otherwise a near-perfect paired sample would
    score below zero by about 2 E||X - X'|| / n. One feature (F = 1: a pendulum's angle at one
    time step) is computed by sorting, in O(n log n) instead of n^2.
    """
    n, m = p.shape[1], q.shape[1]
    if n < 2 or m < 2 or (paired and n != m):
        raise ValueError(f"the energy distance needs at least 2 points per sample (equally many if paired), got {n} and {m}")
    cross = cross_row_means(p, q).sum(-1) * n  # the sum over all pairs
    if paired:
        cross = (cross - (p - q).norm(dim=-1).sum(-1)) / (n * (n - 1))
    else:
        cross = cross / (n * m)
    return 2 * cross - within_means(p) - within_means(q)


def within_means(x: Tensor) -> Tensor:
    """Mean distance between the distinct rows of each batch entry: x (G, n, F) -> (G,)."""
    n = x.shape[1]
    if x.shape[2] == 1:  # in float64 about the mean: the sorted sum cancels large terms
        values = x[..., 0].double()
        return (2 * pair_distance_sums(values - values.mean(-1, keepdim=True)) / (n * (n - 1))).to(x.dtype)
    step = max(1, MAX_BLOCK_ENTRIES // (n * n))
    sums = [_distances(_distance_sums, x[g : g + step]) for g in range(0, len(x), step)]
    return torch.cat(sums) / (n * (n - 1))  # the zero diagonal is skipped by the divisor


def cross_row_means(a: Tensor, b: Tensor) -> Tensor:
    """Each row of b's mean distance to the rows of a, per batch entry: a (G, n, F), b (G, m, F) -> (G, m)."""
    n, m = a.shape[1], b.shape[1]
    if a.shape[2] == 1:
        centred_a, centred_b = _centred(a[..., 0], b[..., 0])
        return (row_distance_sums(centred_a, centred_b) / n).to(a.dtype)
    step = max(1, MAX_BLOCK_ENTRIES // (n * m))
    return torch.cat([_distances(_mean_distances, a[g : g + step], b[g : g + step]) for g in range(0, len(a), step)])


def cell_and_whole_row_means(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Each row of b's mean distance to the rows of a, per cell and between whole rows, from one set of products.

    a (G, n, F) and b (G, m, F) hold G cells of each row (a whole row is its G cells side by side:
    a field's frames and components): -> per cell (G, m), as :func:`cross_row_means`, and whole
    (m,), as :func:`cross_row_means` of the rows flattened. A whole row's squared distance is the
    sum of its cells' squared distances, so both come from one product per cell, half the work of
    computing them apart (:func:`_cell_and_whole_sums`).
    """
    cells, whole = _cell_and_whole_blocks(a, b, within=False)
    return cells / a.shape[1], whole / a.shape[1]


def cell_and_whole_within_means(x: Tensor) -> tuple[Tensor, Tensor]:
    """Mean distance between the distinct rows of x (G, n, F), per cell (G,) and between whole rows (a number),
    as :func:`within_means` of the cells and of the rows flattened; from one set of products."""
    cells, whole = _cell_and_whole_blocks(x, x, within=True)
    pairs = x.shape[1] * (x.shape[1] - 1)
    return cells.sum(-1) / pairs, whole.sum() / pairs


def _cell_and_whole_blocks(a: Tensor, b: Tensor, within: bool) -> tuple[Tensor, Tensor]:
    """Sums over a's rows of :func:`_cell_and_whole_sums`, a's rows taken in blocks of bounded memory."""
    cells, n, m = a.shape[0], a.shape[1], b.shape[1]
    step = max(1, MAX_BLOCK_ENTRIES // (cells * m))
    sums = _compiled(_cell_and_whole_sums) if _worth_compiling(a.device, cells * n * m) else _cell_and_whole_sums
    parts = []
    for start in range(0, n, step):
        rows = torch.arange(start, min(n, start + step), device=a.device)
        parts.append(sums(a[:, start : start + step], b, rows if within else torch.full_like(rows, -1)))
    return sum(part[0] for part in parts), sum(part[1] for part in parts)


def _cell_and_whole_sums(a: Tensor, b: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
    """Per column of b, the summed distances from a's rows, per cell (G, m) and whole (m,): a (G, r, F), b (G, m, F).

    ``rows``: where a's rows sit among b's (a within-sample block, whose own pairs are set to 0),
    or -1 (no pairs of a point with itself). The squared distances come from one matrix product
    per cell (|x|^2 + |y|^2 - 2 x.y), a whole row's as the sum of its cells'; the square root is
    taken where they are positive, with a zero gradient elsewhere (a point's distance to itself).
    """
    squared = a.square().sum(-1, keepdim=True) + b.square().sum(-1).unsqueeze(1) - 2 * a @ b.transpose(1, 2)
    own = rows[:, None] == torch.arange(b.shape[1], device=b.device)
    squared = torch.where(own, 0.0, squared).clamp_min(0)
    return _root(squared).sum(1), _root(squared.sum(0)).sum(0)


def _root(squared: Tensor) -> Tensor:
    """sqrt, with the gradient 0 (not infinite) where the argument is 0."""
    positive = squared > 0
    return torch.where(positive, squared, 1.0).sqrt() * positive


def _distance_sums(x: Tensor) -> Tensor:
    return torch.cdist(x, x).sum((1, 2))


def _mean_distances(a: Tensor, b: Tensor) -> Tensor:
    return torch.cdist(a, b).mean(1)


@functools.cache
def _compiled(function: Callable) -> Callable:
    """``function`` compiled, run eagerly where it cannot be compiled."""
    return EagerFallback(function, compile_generic(function), function, _not_compilable, _fallback_line, log)


def _fallback_line(*samples: Tensor) -> str:
    return "energy distances run eagerly: they could not be compiled"


def _distances(function: Callable, *samples: Tensor) -> Tensor:
    """``function(*samples)`` (a reduction of distance matrices (G, n, m)), compiled on the CPU from
    :data:`COMPILED_ENTRIES` entries on.

    The compiled function computes the distances, their square root and their reduction in one
    pass, forward and backward; the library's ``cdist`` makes several passes over the matrix, which is
    most of a discovery fit's time. Measured on one thread, G, n, m, F = 50, 1024, 700, 20 (an
    advection-diffusion fit's per-time-step distances): 442 ms eager, 163 ms compiled, forward and
    backward, after a compile of 3 s; smaller matrices stay eager, where the compile would not be repaid.
    If it cannot be compiled, it runs eagerly after one line saying why.
    """
    first, last = samples[0], samples[-1]
    large = _worth_compiling(first.device, first.shape[0] * first.shape[1] * last.shape[1])
    return _compiled(function)(*samples) if large else function(*samples)


def _worth_compiling(device: torch.device, entries: int) -> bool:
    """Whether distance matrices of ``entries`` entries in all run compiled: on the CPU, from :data:`COMPILED_ENTRIES`."""
    return device.type == "cpu" and entries >= COMPILED_ENTRIES


def _centred(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """a and b (G, n), (G, m) in float64 about their pooled mean: the sorted sums cancel large terms."""
    a, b = a.double(), b.double()
    shift = torch.cat([a, b], -1).mean(-1, keepdim=True)
    return a - shift, b - shift


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

    if not (bool(torch.isnan(p).any()) or bool(torch.isnan(q).any())):
        return batched_energy(cells(p), cells(q), paired).reshape(steps, channels).float()
    return torch.stack([_measured_energy(a, b, paired) for a, b in zip(cells(p), cells(q))]).reshape(steps, channels).float()


def _measured_energy(a: Tensor, b: Tensor, paired: bool) -> Tensor:
    """The energy distance of one cell over the rows measured there (no NaN; paired: measured on both sides); NaN where
    a side has fewer than 2 such rows, too few for the statistic."""
    keep_a, keep_b = ~torch.isnan(a).any(dim=1), ~torch.isnan(b).any(dim=1)
    if paired:
        keep_a = keep_b = keep_a & keep_b
    a, b = a[keep_a], b[keep_b]
    if len(a) < 2 or len(b) < 2:
        return a.new_tensor(float("nan"))
    return batched_energy(a[None], b[None], paired)[0]


class EnergyDistance(TwoSampleMetric):
    """Energy distance on accumulated samples: ``{"energy"}``, and ``{"energy_per_time": (T, C)}`` when
    ``trajectory_shape`` (T, *obs) says where the trajectory sits in each row; ``paired``: see
    :func:`batched_energy`."""

    def __init__(self, trajectory_shape: tuple[int, ...] | None = None, paired: bool = False, **kwargs) -> None:
        super().__init__(**kwargs)
        self.trajectory_shape = None if trajectory_shape is None else tuple(trajectory_shape)
        self.paired = paired

    reads_missing = True  # the whole rows' distance sees a missing value as 0, each time step's the rows measured there

    def score(self, p: Tensor, q: Tensor) -> dict[str, Tensor]:
        results = {"energy": energy_distance(filled(p), filled(q), self.paired).float()}
        if self.trajectory_shape is not None:
            results["energy_per_time"] = energy_per_time(p, q, self.trajectory_shape, self.paired)
        return results
