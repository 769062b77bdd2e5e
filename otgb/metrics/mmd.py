"""A plain MMD on joint samples (Gretton et al. 2012).

Biased estimate of MMD^2 with the exponentiated-quadratic kernel exp(-||s - s'||^2 / sigma^2)
on features standardised with the pooled mean and std, sigma from the median heuristic
(median pairwise distance of the pooled points).
"""

from __future__ import annotations

import torch
from torch import Tensor


def mmd_rbf(a: Tensor, b: Tensor) -> Tensor:
    """Biased MMD^2 between samples a (N, D) and b (M, D) at the median-heuristic bandwidth."""
    pooled = torch.cat([a, b]).double()
    pooled = (pooled - pooled.mean(0)) / pooled.std(0).clamp_min(1e-12)
    sq = torch.cdist(pooled, pooled).pow(2)
    n = len(a)
    off_diagonal = sq[~torch.eye(len(pooled), dtype=torch.bool, device=sq.device)]
    sigma2 = off_diagonal.sqrt().median().pow(2).clamp_min(1e-12)
    k = torch.exp(-sq / sigma2)
    return (k[:n, :n].mean() + k[n:, n:].mean() - 2 * k[:n, n:].mean()).float()
