"""Maximum mean discrepancy on joint samples (Gretton et al. 2012, "A Kernel Two-Sample Test").

Samples p (n, D) and q (m, D) are standardised with the pooled mean and std, and compared
with the exponentiated-quadratic kernel

    k_sigma(s, s') = exp(-||s - s'||^2 / sigma^2).

Two scalars are reported:

- ``mmd2_median``: the unbiased estimate (Gretton et al. 2012, eq. 3)

      MMD^2_u = sum_{i!=j} k(p_i, p_j) / (n(n-1)) + sum_{i!=j} k(q_i, q_j) / (m(m-1))
                - 2 sum_{i,j} k(p_i, q_j) / (nm)

  at sigma = the median heuristic (median pairwise distance of the pooled points). Unbiased:
  it is 0 on average when p and q have the same distribution, and can be slightly negative.
  On joint samples the median bandwidth is wide (set by the many trajectory features) and
  can miss a wrong conditional that smaller bandwidths see: that is what MMDAgg
  (:mod:`otgb.metrics.mmdagg`) aggregates over bandwidths for.
- ``mmd``: the figure comparable with Table 1 of "Hybrid Generative Modeling for Incomplete
  Physics: Deep Grey-Box Meets Optimal Transport" (ICLR 2025), as in the evaluator of its
  official code (DMML-Geneva/ot-deep-grey-box-model): the biased (V-statistic) estimate
  with the sum of 6 kernels at sigma^2 = h * 2^(i-3), i = 0..5, where h is the mean squared
  distance between distinct pooled points. Biased: positive even for equal distributions (about 2 * 6 / n for large n).

Kernel sums are accumulated over row blocks of ``chunk`` points, so memory is
O(chunk * (n + m)) whatever the sample sizes.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import torch
from torch import Tensor

from otgb.metrics.samples import TwoSampleMetric

PAPER_MULTIPLIERS = tuple(2.0 ** (i - 3) for i in range(6))
MEDIAN_MAX_POINTS = 2000


def standardise(p: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """z-score both samples with the mean and std of the pooled points (constant features -> 0)."""
    pooled = torch.cat([p, q])
    mean, std = pooled.mean(0), pooled.std(0)
    std = torch.where(std > 0, std, torch.ones_like(std))
    return (p - mean) / std, (q - mean) / std


def median_bandwidth(points: Tensor, max_points: int = MEDIAN_MAX_POINTS, seed: int = 0) -> Tensor:
    """Median pairwise Euclidean distance of ``points`` (N, D).

    Above ``max_points`` points the median is taken over a fixed-seed random subset of that
    many points (its pairwise distances), which keeps the cost O(max_points^2).
    """
    if len(points) > max_points:
        g = torch.Generator().manual_seed(seed)
        points = points[torch.randperm(len(points), generator=g)[:max_points].to(points.device)]
    distances = torch.pdist(points)
    if distances.numel() == 0:
        raise ValueError("the median heuristic needs at least 2 points")
    median = distances.median()
    return median if median > 0 else distances.max().clamp_min(1.0)


def mean_sq_distance(points: Tensor) -> Tensor:
    """Mean of ||s_i - s_j||^2 over distinct pairs, in O(N D): (2N sum_i |s_i|^2 - 2 |sum_i s_i|^2) / (N(N-1))."""
    n = len(points)
    total = 2 * n * (points**2).sum() - 2 * (points.sum(0) ** 2).sum()
    return total / (n * (n - 1))


def sq_distance_blocks(a: Tensor, b: Tensor, chunk: int) -> Iterator[tuple[int, Tensor]]:
    """Yield (start, ||a[start:start+chunk] - b||^2) row block by row block."""
    b_sq = (b**2).sum(1)
    for start in range(0, len(a), chunk):
        block = a[start : start + chunk]
        yield start, ((block**2).sum(1)[:, None] + b_sq[None, :] - 2 * block @ b.T).clamp_min_(0.0)


def kernel_sum(a: Tensor, b: Tensor, sq_bandwidths: Tensor, chunk: int = 1024) -> Tensor:
    """sum_{i,j} exp(-||a_i - b_j||^2 / sigma_l^2) for each sigma_l^2 in ``sq_bandwidths`` -> (L,)."""
    total = torch.zeros(len(sq_bandwidths), dtype=a.dtype, device=a.device)
    for _, d2 in sq_distance_blocks(a, b, chunk):
        for index, sq_bandwidth in enumerate(sq_bandwidths):  # one (chunk, m) block in memory at a time
            total[index] += torch.exp(-d2 / sq_bandwidth).sum()
    return total


def mmd2(p: Tensor, q: Tensor, sq_bandwidths: Tensor, unbiased: bool = True, chunk: int = 1024) -> Tensor:
    """MMD^2 between p (n, D) and q (m, D) for each kernel exp(-d^2 / sigma_l^2) -> (L,).

    ``unbiased`` drops the i = j terms within each sample (k = 1 there), as in the module
    docstring's MMD^2_u; otherwise the biased V-statistic.
    """
    n, m = len(p), len(q)
    if n < 2 or m < 2:
        raise ValueError(f"MMD needs at least 2 points per sample, got {n} and {m}")
    s_pp, s_qq = kernel_sum(p, p, sq_bandwidths, chunk), kernel_sum(q, q, sq_bandwidths, chunk)
    s_pq = kernel_sum(p, q, sq_bandwidths, chunk)
    if unbiased:
        return (s_pp - n) / (n * (n - 1)) + (s_qq - m) / (m * (m - 1)) - 2 * s_pq / (n * m)
    return s_pp / n**2 + s_qq / m**2 - 2 * s_pq / (n * m)


def mmd_median(p: Tensor, q: Tensor, chunk: int = 1024) -> Tensor:
    """Unbiased MMD^2 at the median-heuristic bandwidth, on pooled-standardised features."""
    p, q = standardise(*_as_float(p, q))
    sigma = median_bandwidth(torch.cat([p, q]))
    return mmd2(p, q, (sigma**2).reshape(1), unbiased=True, chunk=chunk)[0]


def mmd_multiscale(p: Tensor, q: Tensor, chunk: int = 1024) -> Tensor:
    """Biased MMD^2 with the sum of 6 kernels at sigma^2 = h * 2^(i-3) (the paper-code figure)."""
    p, q = standardise(*_as_float(p, q))
    h = mean_sq_distance(torch.cat([p, q]))
    sq_bandwidths = h * torch.tensor(PAPER_MULTIPLIERS, dtype=p.dtype, device=p.device)
    return mmd2(p, q, sq_bandwidths, unbiased=False, chunk=chunk).sum()


def _as_float(p: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """2-D floating samples with the same number of features (float64 kept, others -> float32)."""
    if p.dim() != 2 or q.dim() != 2 or p.shape[1] != q.shape[1]:
        raise ValueError(f"two-sample inputs must be (n, D) and (m, D), got {tuple(p.shape)} and {tuple(q.shape)}")
    dtype = torch.float64 if torch.float64 in (p.dtype, q.dtype) else torch.float32
    return p.to(dtype), q.to(dtype)


class MMD(TwoSampleMetric):
    """MMD between accumulated samples: ``{"mmd": paper-code figure, "mmd2_median": unbiased MMD^2}``.

    Args:
        chunk: rows of the kernel matrix held in memory at a time.
        **kwargs: torchmetrics Metric options (e.g. ``sync_on_compute``).
    """

    def __init__(self, chunk: int = 1024, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.chunk = chunk

    def score(self, p: Tensor, q: Tensor) -> dict[str, Tensor]:
        p, q = p.double(), q.double()
        return {"mmd": mmd_multiscale(p, q, self.chunk).float(), "mmd2_median": mmd_median(p, q, self.chunk).float()}
