"""Pointwise errors for one-to-one tasks, as in the paper's official evaluator.

    ABS ERR = mean_i [ mean_t |y_hat_i(t) - y_i(t)| ]
    N-RMSE  = mean_i [ sqrt(mean_t (y_hat_i(t) - y_i(t))^2) ] / (max(y) - min(y)),

with max/min taken over the whole evaluation set of targets y. The mean over t runs over
every non-batch dimension (time and observed components).
"""

from __future__ import annotations

from torch import Tensor


def abs_err(pred: Tensor, target: Tensor) -> Tensor:
    """Per-sample mean absolute error, (N, ...) x (N, ...) -> (N,)."""
    return (pred - target).abs().flatten(1).mean(dim=1)


def nrmse(pred: Tensor, target: Tensor, value_range: float | Tensor) -> Tensor:
    """Per-sample RMSE divided by the target range of the whole set, -> (N,)."""
    return ((pred - target) ** 2).flatten(1).mean(dim=1).sqrt() / value_range
