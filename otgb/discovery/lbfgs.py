"""The optimiser loop of every distribution-matching fit: L-BFGS on the mean discrepancy of fixed simulated samples.

A fit (the coefficients' priors, :mod:`otgb.discovery.refine`; f_p's recalibrated priors,
:mod:`otgb.discovery.recalibration`; a parametric form's parameters, :mod:`otgb.discovery.forms`) holds its
simulated inputs fixed, so the discrepancy (:func:`otgb.discovery.discrepancy.discrepancy_and_rows`) is a smooth
deterministic function of the parameters, and L-BFGS with a strong-Wolfe line search can follow the narrow valleys
that correlated parameters make. Its gradient is taken a chunk of trajectories at a time
(:mod:`otgb.discovery.chunked`).

A refit of the same parameters on other data from where a fit ended (a fold's refit, :mod:`otgb.discovery.crossfit`)
starts with that fit's :class:`Curvature`: L-BFGS's memory of its last steps. The discrepancy's curvature near the
optimum is nearly the same on the other data, so the first step is already a quasi-Newton one, where a cold start
spends its first iterations learning the curvature again.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from otgb.discovery.chunked import Simulate, backward_in_chunks, chunk_size
from otgb.discovery.discrepancy import Target, discrepancy_and_rows

# The loss L-BFGS sees where the model diverges: finite, so that its strong-Wolfe line search
# backtracks (from an infinite value its cubic interpolation gives NaN, and every parameter becomes NaN).
DIVERGED_LOSS = 1e10


MEMORY = ("old_dirs", "old_stps", "ro", "H_diag")  # the keys of torch's L-BFGS state that hold its curvature


@dataclass
class Curvature:
    """L-BFGS's curvature memory at the end of a fit (empty before one): its last steps, their gradient changes, the
    scale of its initial inverse Hessian."""

    memory: dict = field(default_factory=dict)

    def load(self, optimiser: torch.optim.LBFGS) -> None:
        """Start ``optimiser`` from this memory: its first direction the quasi-Newton one, no step of its own taken
        yet (a zero last step adds nothing to the memory)."""
        if not self.memory:
            return
        first = optimiser.param_groups[0]["params"][0]
        flat = torch.cat([p.detach().reshape(-1) for p in optimiser.param_groups[0]["params"]])
        moved = {k: [t.to(flat.device) for t in v] if isinstance(v, list) else v for k, v in self.memory.items()}
        optimiser.state[first].update(moved | {"n_iter": 1, "d": torch.zeros_like(flat), "t": 1.0})
        optimiser.state[first]["prev_flat_grad"] = torch.zeros_like(flat)

    def save(self, optimiser: torch.optim.LBFGS) -> None:
        state = optimiser.state[optimiser.param_groups[0]["params"][0]]
        self.memory = {k: [t.clone() for t in state[k]] if isinstance(state[k], list) else state[k] for k in MEMORY if k in state}


@dataclass(frozen=True)
class Ended:
    """Where a fit ended, for a refit on other data to start from: the module holding its parameters and its
    optimiser's curvature."""

    module: torch.nn.Module
    curvature: Curvature

    def restart(self) -> tuple[torch.nn.Module, Curvature]:
        """Copies of both, for one refit."""
        return copy.deepcopy(self.module), copy.deepcopy(self.curvature)


def minimise(
    parameters: list[Tensor], simulate: Simulate, n: int, target: Target, samples: int, steps: int,
    is_finite: Callable[[], bool], curvature: Curvature | None = None,
) -> list[float]:  # fmt: skip
    """Minimise the mean discrepancy to ``target`` of the n simulated trajectories (``samples`` equal samples one
    after the other, each compared with the target) over ``parameters``, ``steps`` L-BFGS iterations; returns the
    finite losses evaluated. Where ``is_finite()`` fails after the last step (a line search that ran into parameters
    whose solves diverge), the parameters are set to the best iterate evaluated. ``curvature`` (where given) starts
    the optimiser from its memory and holds the optimiser's at the end."""
    warm = curvature is not None and bool(curvature.memory)
    evaluations = steps if warm else 2 * steps  # a warm start's first step is a quasi-Newton one: little to search
    optimiser = torch.optim.LBFGS(parameters, lr=1, max_iter=steps, max_eval=evaluations, line_search_fn="strong_wolfe")
    if warm:
        curvature.load(optimiser)
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
    if curvature is not None:
        curvature.save(optimiser)
    if losses and not is_finite():
        restore(parameters, best)
    return losses


@torch.no_grad()
def restore(parameters: list[Tensor], values: list[Tensor]) -> None:
    """Set ``parameters`` to ``values`` (a fit's best iterate)."""
    for parameter, value in zip(parameters, values):
        parameter.copy_(value)
