"""Exact gradients of a loss of many simulated trajectories, with the autograd graph of only a few in memory.

A distribution-matching loss (:func:`otgb.discovery.discrepancy.discrepancy`) compares every simulated
trajectory with every other, so it does not split into a sum over chunks of trajectories; but its
gradient does, by the chain rule. :func:`backward_in_chunks` takes it in two passes:

1. simulate all n trajectories without a graph, evaluate the loss on them and take its gradient
   g with respect to the trajectories (cheap: the loss is a function of n small arrays);
2. simulate again, a chunk of trajectories at a time with a graph, and back-propagate g's rows
   of that chunk, so that the gradients of the parameters the simulation depends on accumulate.

The fixed-step solvers of :class:`otgb.physics.base.PhysicsModel` solve each trajectory on its own
(no step size shared by the batch), so the second pass differentiates the same function at the same
points and the gradient is the whole batch's. (Measurement noise, where it is in force, is added to
the observations and drawn per chunk's shape; being additive, it leaves the derivatives unchanged.)
The chunk is as large as :data:`GRAPH_BYTES` of saved tensors allow, measured on one trajectory: a
32x32 reaction-diffusion solve with twenty library terms saves ~9 MB per trajectory and grows the
process by ~30 MB, so a fit of 1024 trajectories in one graph needs ~31 GB.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

GRAPH_BYTES = 1024**3  # the storages autograd keeps for one chunk of simulated trajectories: at most this many bytes

Simulate = Callable[[slice], Tensor]  # the trajectories of the given rows, with a graph where grad is enabled


def backward_in_chunks(
    simulate: Simulate, n: int, loss_of: Callable[[Tensor], Tensor], size: int, groups: int = 1
) -> tuple[Tensor, Tensor]:
    """``loss_of(simulate(slice(0, n)))`` and the trajectories, both detached; where the loss is finite, its
    gradient is accumulated into the ``.grad`` of the leaves that ``simulate`` depends on: in one pass where ``size``
    (:func:`chunk_size`) covers all n trajectories, else in two, ``size`` trajectories at a time (module docstring).

    ``groups``: the loss is a sum over that many equal blocks of the n rows, each a function of its own rows
    alone (an interval's perturbed models, :mod:`otgb.discovery.intervals`); its value and gradient are then
    taken a block at a time (two passes), so that the loss's own graph, the distances between every pair of
    a block's trajectories, is held for one block only."""
    one_pass = size >= n and groups == 1
    with torch.set_grad_enabled(one_pass):
        simulated = simulate(slice(0, n))
    if one_pass:
        loss = loss_of(simulated)
        if bool(torch.isfinite(loss)):
            loss.backward()
        return loss.detach(), simulated.detach()
    loss, gradient = _loss_and_gradient(loss_of, simulated, groups)
    if gradient is None:
        return loss, simulated
    for start in range(0, n, size):
        rows = slice(start, min(start + size, n))
        simulate(rows).backward(gradient[rows])
    return loss, simulated


def _loss_and_gradient(loss_of: Callable[[Tensor], Tensor], rows: Tensor, groups: int) -> tuple[Tensor, Tensor | None]:
    """The loss of ``rows`` (the sum of ``loss_of`` over ``groups`` equal blocks of them) and its gradient, a block at
    a time; no gradient where the loss is not finite."""
    total, gradients = torch.zeros((), dtype=rows.dtype), []
    for block in rows.chunk(groups):
        leaf = block.detach().requires_grad_()
        loss = loss_of(leaf)
        total = total + loss.detach()
        if not bool(torch.isfinite(total)):
            return total, None
        gradients.append(torch.autograd.grad(loss, leaf)[0])
    return total, torch.cat(gradients)


def chunk_size(simulate: Simulate, n: int, budget: int | None = None) -> int:
    """How many of the n trajectories fit in ``budget`` bytes (default :data:`GRAPH_BYTES`) of saved tensors, measured
    on the first (a solve of one trajectory: once per fit, not per evaluation)."""
    budget = GRAPH_BYTES if budget is None else budget
    per_trajectory = saved_bytes(lambda: simulate(slice(0, 1)))
    return max(1, min(n, budget // max(per_trajectory, 1)))


def saved_bytes(run: Callable[[], object]) -> int:
    """The bytes of the storages that autograd keeps for the backward pass of ``run()`` (each storage once)."""
    storages: dict[int, int] = {}

    def pack(tensor: Tensor) -> Tensor:
        storage = tensor.untyped_storage()
        storages[storage.data_ptr()] = storage.nbytes()
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        run()
    return sum(storages.values())
