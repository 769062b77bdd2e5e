"""Gradient averaging for alternating updates under Lightning's DDP.

Algorithm 1 alternates map and critic updates, each backward reaching one network only. DDP's
reducer averages every registered parameter's gradient at every backward and fails on the
network that a backward did not reach (the critic's in a map update, the map's in a critic
update). otgb turns the reducer off for the training step and averages the gradients of the
network being updated just before its optimiser steps: each process simulates its own sources
and draws, and all processes take the same step, so their weights stay equal.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from lightning.pytorch.strategies import Strategy
from torch import nn
from torch._utils import _flatten_dense_tensors, _unflatten_dense_tensors
from torch.nn.parallel import DistributedDataParallel


def without_gradient_sync(strategy: Strategy) -> None:
    """Turn the DDP reducer's gradient all-reduce off (what ``DistributedDataParallel.no_sync`` does) for a step."""
    if isinstance(strategy.model, DistributedDataParallel):
        strategy.model.require_backward_grad_sync = False


def average_gradients(parameters: Iterable[nn.Parameter], strategy: Strategy) -> None:
    """Average the gradients of ``parameters`` over the processes; every process calls it at the same point.

    A parameter without a gradient counts as a zero gradient, so the collective has the same
    size on every process.
    """
    if getattr(strategy, "world_size", 1) <= 1:
        return
    parameters = [p for p in parameters if p.requires_grad]
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in parameters]
    flat = strategy.reduce(_flatten_dense_tensors(grads), reduce_op="mean")
    for parameter, grad in zip(parameters, _unflatten_dense_tensors(flat, grads)):
        parameter.grad = grad
