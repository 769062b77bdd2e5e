"""The optimiser loop of every distribution-matching fit: L-BFGS on the mean discrepancy of fixed simulated samples.

A fit (the coefficients' priors, :mod:`otgb.discovery.refine`; f_p's recalibrated priors,
:mod:`otgb.discovery.recalibration`; a parametric form's parameters, :mod:`otgb.discovery.forms`) holds its
simulated inputs fixed, so the discrepancy (:func:`otgb.discovery.discrepancy.discrepancy_and_rows`) is a smooth
deterministic function of the parameters, and L-BFGS with a strong-Wolfe line search can follow the narrow valleys
that correlated parameters make. Its gradient is taken a chunk of trajectories at a time
(:mod:`otgb.discovery.chunked`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from otgb.discovery.chunked import Simulate, backward_in_chunks, chunk_size
from otgb.discovery.discrepancy import Target, discrepancy_and_rows

# The loss L-BFGS sees where the model diverges: finite, so that its strong-Wolfe line search
# backtracks (from an infinite value its cubic interpolation gives NaN, and every parameter becomes NaN).
DIVERGED_LOSS = 1e10


def minimise(
    parameters: list[Tensor], simulate: Simulate, n: int, target: Target, samples: int, steps: int,
    is_finite: Callable[[], bool],
) -> list[float]:  # fmt: skip
    """Minimise the mean discrepancy to ``target`` of the n simulated trajectories (``samples`` equal samples one
    after the other, each compared with the target) over ``parameters``, ``steps`` L-BFGS iterations; returns the
    finite losses evaluated. Where ``is_finite()`` fails after the last step (a line search that ran into parameters
    whose solves diverge), the parameters are set to the best iterate evaluated."""
    optimiser = torch.optim.LBFGS(parameters, lr=1, max_iter=steps, max_eval=2 * steps, line_search_fn="strong_wolfe")
    losses: list[float] = []
    best: list[Tensor] = []  # the parameters of the lowest finite loss evaluated
    size = chunk_size(simulate, n)

    def closure() -> Tensor:
        optimiser.zero_grad()
        mean_of_samples = lambda simulated: discrepancy_and_rows(simulated, target)[0] / samples  # noqa: E731
        loss, _ = backward_in_chunks(simulate, n, mean_of_samples, size, groups=samples)
        if not torch.isfinite(loss):  # trajectories diverged, or grew so large that their distances overflow
            return torch.tensor(DIVERGED_LOSS)
        value = float(loss)
        if not losses or value < min(losses):
            best[:] = [p.detach().clone() for p in parameters]
        losses.append(value)
        return loss

    optimiser.step(closure)
    if losses and not is_finite():
        restore(parameters, best)
    return losses


@torch.no_grad()
def restore(parameters: list[Tensor], values: list[Tensor]) -> None:
    """Set ``parameters`` to ``values`` (a fit's best iterate)."""
    for parameter, value in zip(parameters, values):
        parameter.copy_(value)
