"""Joint samples (theta, x0, y) and the base of the two-sample metrics.

The paper ("Hybrid Generative Modeling for Incomplete Physics: Deep Grey-Box Meets Optimal
Transport", ICLR 2025) evaluates on the joint distribution pi(theta, x0, y): a model is only
right if each generated y fits its own inputs, so every sample row holds the inputs next to
the trajectory.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat


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
    :meth:`score`, which subclasses define and which returns named scalars.
    """

    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.add_state("p", default=[], dist_reduce_fx="cat")
        self.add_state("q", default=[], dist_reduce_fx="cat")

    def update(self, p: Tensor, q: Tensor) -> None:
        if p.dim() != 2 or q.dim() != 2 or p.shape[1] != q.shape[1]:
            raise ValueError(f"{type(self).__name__}.update: expected (n, D) and (m, D), got {tuple(p.shape)}, {tuple(q.shape)}")
        for name, rows in (("p", p), ("q", q)):
            if not torch.isfinite(rows).all():
                raise ValueError(f"{type(self).__name__}.update: sample {name} contains NaN/Inf")
        self.p.append(p.detach())
        self.q.append(q.detach())

    def compute(self) -> dict[str, Tensor]:
        return self.score(dim_zero_cat(self.p), dim_zero_cat(self.q))

    def score(self, p: Tensor, q: Tensor) -> dict[str, Tensor]:
        raise NotImplementedError
