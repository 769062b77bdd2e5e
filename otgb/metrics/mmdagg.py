"""MMDAgg: an MMD two-sample test aggregated over kernel bandwidths (Schrab et al. 2023, "MMD
Aggregated Two-Sample Test").

One unbiased MMD^2_u (see :mod:`otgb.metrics.mmd`) per bandwidth sigma_l = 2^l * sigma_med
(sigma_med: median heuristic on pooled-standardised points; l in [-4, 0] by default, the
collection used by the official code of "Hybrid Generative Modeling for Incomplete Physics:
Deep Grey-Box Meets Optimal Transport" (ICLR 2025), DMML-Geneva/ot-deep-grey-box-model),
weights w_l = 1/L. Permutations of the pooled points (valid for any sample sizes) give the
null distribution:

1. ``n_permutations`` (B1) permuted statistics per bandwidth give each bandwidth's
   permutation p-value p_l = (1 + #{b: M_l^b >= M_l}) / (B1 + 1).
2. The aggregated statistic is t = min_l p_l / w_l (small = evidence against H0).
3. ``n_level`` (B2) further permutations give t's null distribution; the adjusted p-value is
   p_agg = (1 + #{b: t^b <= t}) / (B2 + 1), and the test rejects at level alpha iff
   p_agg <= alpha.

Permutations: of all pooled points (any sizes), or, for ``paired`` samples (equal sizes, row
i of p and row i of q share their inputs, as model and DGP draws on the same (theta, x0) do),
swaps within a random half of the pairs: the wild bootstrap's sign flips, and the exact null
for such data. Plain permutations would break the shared inputs apart and make the test
very conservative there.

Each p_l is at least 1/(B1 + 1), so t is at least L/(B1 + 1), and null draws reach that
floor too: B1 must be large against L/alpha (checked: (B1 + 1) alpha >= 2L).

Step 3 is MMDAgg's level correction: rejecting iff p_agg <= alpha is the same as some
bandwidth's p-value falling below u_alpha * w_l, where u_alpha (found by bisection in the
original) is the alpha-quantile of the null t^b. Reported: the decision, p_agg and MMD^2_u
at the bandwidth with the smallest weighted p-value
(ties broken by the statistic's z-score against its permutations).

Ties: a permuted statistic equal to the observed one counts as at least as extreme (">="),
and a null t^b equal to t as at most as large ("<="). Equal in exact arithmetic must stay
equal in the computed one: on bit-identical paired samples (a deterministic DGP against
itself) every swap leaves MMD^2_u unchanged, but float32 sums in a different order come out
up to ~4e-7 apart, about half of them below the observed value, and p_agg fell to 0.02-0.05
(a rejection of two identical samples). So the statistics are computed in float64 (from the
standardised points on) and ties are counted with an absolute tolerance ``TIE_TOLERANCE``
= 1e-9: far above float64 rounding of these sums (kernels are bounded by 1, so MMD^2_u is
O(1) and its rounding O(1e-15)), far below any real permutation fluctuation (O(1/n)). The
same tolerance applies to t, which lives on a grid of spacing L/(B1 + 1).

All permuted statistics come from one pass over the kernel matrix in row blocks: with a the
0/1 membership of p under a permutation and K~ the kernel matrix with zero diagonal,

    MMD^2_u = a'K~a / (n(n-1)) + b'K~b / (m(m-1)) - 2 a'K~b / (nm),   b = 1 - a,

so K~ A for the membership matrix A of all permutations is all that is needed: memory
O(chunk * (n + m) + (n + m) * (B1 + B2)).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from otgb.metrics.mmd import _as_float, median_bandwidth, sq_distance_blocks, standardise
from otgb.metrics.samples import TwoSampleMetric

PAPER_EXPONENTS = (-4, -3, -2, -1, 0)
TIE_TOLERANCE = 1e-9


def mmdagg(
    p: Tensor,
    q: Tensor,
    alpha: float = 0.05,
    exponents: tuple[int, ...] = PAPER_EXPONENTS,
    n_permutations: int = 500,
    n_level: int = 500,
    seed: int = 0,
    chunk: int = 1024,
    paired: bool = False,
) -> dict[str, Tensor]:
    """Aggregated MMD permutation test of p (n, D) vs q (m, D).

    ``paired``: row i of p and row i of q belong together (e.g. the same inputs theta, x0
    with a DGP draw and a model draw); the permutations then swap within pairs, which is the
    exact null of such data (see the module docstring).

    Returns ``mmdagg_reject`` (1.0 or 0.0 at level ``alpha``), ``mmdagg_pvalue`` (adjusted,
    p_agg above) and ``mmdagg_mmd2`` (MMD^2_u at the most significant bandwidth).
    """
    check_options(alpha, exponents, n_permutations, n_level)
    p, q = standardise(*(x.double() for x in _as_float(p, q)))  # float64: see "Ties" in the module docstring
    n, m = len(p), len(q)
    if n < 2 or m < 2:
        raise ValueError(f"mmdagg needs at least 2 points per sample, got {n} and {m}")
    pooled = torch.cat([p, q])
    sigma = median_bandwidth(pooled, seed=seed)
    sq_bandwidths = (sigma * 2.0 ** torch.tensor(exponents, dtype=p.dtype, device=p.device)) ** 2
    if paired and n != m:
        raise ValueError(f"mmdagg: paired samples need equal sizes, got {n} and {m}")
    membership = _memberships(n, m, n_permutations + n_level, seed, p.device, paired).to(p.dtype)
    stats = _permuted_mmd2(pooled, membership, n, sq_bandwidths, chunk)  # (L, 1 + B1 + B2)

    observed, null, level_draws = stats[:, :1], stats[:, 1 : 1 + n_permutations], stats[:, 1 + n_permutations :]
    weights = torch.full((len(exponents), 1), 1.0 / len(exponents), dtype=p.dtype, device=p.device)
    t_per_bandwidth = (_pvalues(observed, null) / weights)[:, 0]
    t_null = (_pvalues(level_draws, null) / weights).min(dim=0).values
    p_agg = (1 + (t_null <= t_per_bandwidth.min() + TIE_TOLERANCE).sum()) / (n_level + 1)
    z = (observed[:, 0] - null.mean(1)) / null.std(1).clamp_min(torch.finfo(null.dtype).tiny)
    best = torch.where(t_per_bandwidth == t_per_bandwidth.min(), z, -torch.inf).argmax()  # ties: the largest z-score
    return {
        "mmdagg_reject": (p_agg <= alpha).to(torch.float32),
        "mmdagg_pvalue": p_agg.to(torch.float32),
        "mmdagg_mmd2": observed[best, 0].to(torch.float32),
    }


def check_options(alpha: float, exponents: tuple[int, ...], n_permutations: int, n_level: int) -> None:
    """Reject settings under which the test cannot reach its level."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"mmdagg: alpha={alpha}, expected a level in (0, 1)")
    if n_level < 1 or not exponents:
        raise ValueError(f"mmdagg: need n_level >= 1 and some exponents; got n_level={n_level}, exponents={exponents}")
    if (n_permutations + 1) * alpha < 2 * len(exponents):
        needed = math.ceil(2 * len(exponents) / alpha)
        raise ValueError(
            f"mmdagg: n_permutations={n_permutations} cannot resolve level {alpha} over {len(exponents)} bandwidths: the "
            f"smallest adjusted p-value is about {len(exponents)}/(n_permutations + 1); use >= {needed}"
        )


def _memberships(n: int, m: int, n_perm: int, seed: int, device: torch.device, paired: bool) -> Tensor:
    """(n + m, 1 + n_perm) 0/1 matrix: column 0 the true split (first n rows are p), then permutations.

    ``paired``: each permutation swaps p_i and q_i for a random half of the pairs (n = m).
    """
    g = torch.Generator().manual_seed(seed + 1)
    if paired:
        swap = torch.rand(n, n_perm, generator=g) < 0.5
        permuted = torch.cat([~swap, swap])
    else:
        ranks = torch.rand(n_perm, n + m, generator=g).argsort(dim=1).argsort(dim=1)
        permuted = (ranks < n).T
    identity = (torch.arange(n + m) < n)[:, None]
    return torch.cat([identity, permuted], dim=1).to(device)


def _permuted_mmd2(pooled: Tensor, membership: Tensor, n: int, sq_bandwidths: Tensor, chunk: int) -> Tensor:
    """MMD^2_u for every membership column and bandwidth -> (L, columns), in the dtype of ``pooled``.

    :func:`mmdagg` passes float64 points and memberships, so that statistics equal in exact
    arithmetic agree to far within ``TIE_TOLERANCE``.
    """
    m = len(pooled) - n
    n_bw, n_col = len(sq_bandwidths), membership.shape[1]
    aka, akb, bkb = (torch.zeros(n_bw, n_col, dtype=pooled.dtype, device=pooled.device) for _ in range(3))
    for start, d2 in sq_distance_blocks(pooled, pooled, chunk):
        rows = torch.arange(len(d2), device=d2.device)
        a = membership[start : start + len(d2)]
        for index, sq_bw in enumerate(sq_bandwidths):
            k = torch.exp(-d2 / sq_bw)
            k[rows, start + rows] = 0.0
            k_a = k @ membership
            k_b = k.sum(1, keepdim=True) - k_a
            aka[index] += (a * k_a).sum(0)
            akb[index] += (a * k_b).sum(0)
            bkb[index] += ((1 - a) * k_b).sum(0)
    return aka / (n * (n - 1)) + bkb / (m * (m - 1)) - 2 * akb / (n * m)


def _pvalues(statistics: Tensor, null: Tensor) -> Tensor:
    """Permutation p-values (1 + #{null >= s}) / (B + 1) per bandwidth row: (L, S) x (L, B) -> (L, S).

    A null value within ``TIE_TOLERANCE`` below s is a tie and counts (see the module docstring).
    """
    exceed = (null[:, None, :] >= statistics[:, :, None] - TIE_TOLERANCE).sum(dim=2)
    return (1 + exceed).to(statistics.dtype) / (null.shape[1] + 1)


class MMDAgg(TwoSampleMetric):
    """The MMDAgg test on accumulated samples: ``{"mmdagg_reject", "mmdagg_pvalue", "mmdagg_mmd2"}``.

    Args:
        alpha: level of the test.
        exponents: the bandwidths 2^l * sigma_med, one per exponent l.
        n_permutations: B1, permutations for each bandwidth's p-value.
        n_level: B2, permutations for the null distribution of the aggregated statistic.
        seed: seed of the permutations and of the median heuristic's subset.
        chunk: rows of the kernel matrix held in memory at a time.
        paired: row i of p and row i of q share their inputs (swaps within pairs).
        **kwargs: torchmetrics Metric options (e.g. ``sync_on_compute``).
    """

    def __init__(
        self,
        alpha: float = 0.05,
        exponents: tuple[int, ...] = PAPER_EXPONENTS,
        n_permutations: int = 500,
        n_level: int = 500,
        seed: int = 0,
        chunk: int = 1024,
        paired: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        check_options(alpha, tuple(exponents), n_permutations, n_level)
        self.options = dict(
            alpha=alpha,
            exponents=tuple(exponents),
            n_permutations=n_permutations,
            n_level=n_level,
            seed=seed,
            chunk=chunk,
            paired=paired,
        )

    def score(self, p: Tensor, q: Tensor) -> dict[str, Tensor]:
        return mmdagg(p, q, **self.options)
