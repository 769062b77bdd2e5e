"""Pointwise errors for one-to-one tasks, as in the evaluator of the paper's official code
(DMML-Geneva/ot-deep-grey-box-model, for "Hybrid Generative Modeling for Incomplete Physics:
Deep Grey-Box Meets Optimal Transport", ICLR 2025).

    ABS ERR = mean_i [ mean_t |y_hat_i(t) - y_i(t)| ]
    N-RMSE  = mean_i [ sqrt(mean_t (y_hat_i(t) - y_i(t))^2) ] / (max(y) - min(y)),

with max/min taken over the whole evaluation set of targets y. The mean over t runs over
every non-batch dimension (time and observed components), over the measured values only where
a target has missing ones (NaN), and max/min over its measured values. The metrics also report the
standard deviation over the inputs i (``<name>_std``), the spread in the paper's tables.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric


def abs_err(pred: Tensor, target: Tensor) -> Tensor:
    """Per-sample mean absolute error, (N, ...) x (N, ...) -> (N,)."""
    _check_pair(pred, target)
    return (pred - target).abs().flatten(1).nanmean(dim=1)


def nrmse(pred: Tensor, target: Tensor, value_range: float | Tensor | None = None) -> Tensor:
    """Per-sample RMSE divided by the target range (default: the range of ``target``), -> (N,)."""
    _check_pair(pred, target)
    if value_range is None:
        measured = target[~torch.isnan(target)]
        value_range = measured.max() - measured.min()
    return ((pred - target) ** 2).flatten(1).nanmean(dim=1).sqrt() / value_range


def _check_pair(pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape or pred.dim() < 2:
        raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)}: expected equal shapes (N, ...)")


class _PerSampleMean(Metric):
    """Mean and std over samples of a per-sample error, accumulated as sums (sync: sum)."""

    full_state_update = False
    name = ""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        for state in ("total", "total_sq", "count"):
            self.add_state(state, default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def _accumulate(self, values: Tensor) -> None:
        values = values.double()
        self.total += values.sum()
        self.total_sq += (values**2).sum()
        self.count += values.numel()

    def _mean_std(self, scale: Tensor | float = 1.0) -> dict[str, Tensor]:
        mean = self.total / self.count
        var = (self.total_sq / self.count - mean**2).clamp_min(0.0) * self.count / (self.count - 1).clamp_min(1)
        return {self.name: (mean / scale).float(), f"{self.name}_std": (var.sqrt() / scale).float()}


class AbsErr(_PerSampleMean):
    """ABS ERR over batches of (pred, target) pairs of shape (N, ...): ``{"abs_err", "abs_err_std"}``."""

    name = "abs_err"

    def update(self, pred: Tensor, target: Tensor) -> None:
        self._accumulate(abs_err(pred, target))

    def compute(self) -> dict[str, Tensor]:
        return self._mean_std()


class NRMSE(_PerSampleMean):
    """N-RMSE over batches: per-sample RMSEs are summed, the target range is tracked over all
    batches (and processes) and divides at the end: ``{"nrmse", "nrmse_std"}``."""

    name = "nrmse"

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.add_state("target_max", default=torch.tensor(-torch.inf, dtype=torch.float64), dist_reduce_fx="max")
        self.add_state("target_min", default=torch.tensor(torch.inf, dtype=torch.float64), dist_reduce_fx="min")

    def update(self, pred: Tensor, target: Tensor) -> None:
        self._accumulate(nrmse(pred, target, value_range=1.0))
        measured = target[~torch.isnan(target)]
        self.target_max = torch.maximum(self.target_max, measured.max().double())
        self.target_min = torch.minimum(self.target_min, measured.min().double())

    def compute(self) -> dict[str, Tensor]:
        return self._mean_std(scale=self.target_max - self.target_min)
