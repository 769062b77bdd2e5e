"""Gradient averaging for alternating updates under Lightning's DDP.

Algorithm 1 alternates map and critic updates, each backward reaching one network only. DDP's
reducer averages every registered parameter's gradient at every backward and fails on the
network that a backward did not reach (the critic's in a map update, the map's in a critic
update). otgb turns the reducer off for the training step and averages the gradients of the
network being updated just before its optimiser steps: each process simulates its own sources
and draws, and all processes take the same step, so their weights stay equal.
"""

from __future__ import annotations

import signal
from collections.abc import Iterable
from types import FrameType

import torch
from lightning import Trainer
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


class SigtermAgreement:
    """Under several processes, SIGTERM stops every process after the same training step.

    Lightning's SIGTERM handler broadcasts a flag from inside the signal handler: that collective
    meets whatever collective the other processes are in (here the gradient averaging) and the
    run hangs until the scheduler kills it, with no checkpoint of the step it stopped at. And a
    process that alone got the signal would stop alone. Here the handler only notes the signal
    (and passes it on to the processes Lightning started); after each training step the
    processes agree on it (an all-reduce of one flag) and all of them stop there, so that
    :class:`otgb.command.BestAndLastCheckpoint` saves ``last.ckpt`` from all of them together.
    """

    def __init__(self) -> None:
        self.received = False
        self.trainer: Trainer | None = None

    def install(self, trainer: Trainer) -> None:
        """Replace Lightning's SIGTERM handler (registered before training starts) when there are several processes."""
        if trainer.world_size > 1:
            self.trainer, self.received = trainer, False
            signal.signal(signal.SIGTERM, self.note)

    def note(self, signum: int, frame: FrameType | None) -> None:
        launcher = self.trainer.strategy.launcher if self.trainer is not None else None
        if not self.received and launcher is not None:
            launcher.kill(signum)  # the processes Lightning started itself (none under torchrun or SLURM)
        self.received = True

    def agree(self, trainer: Trainer) -> None:
        """Every process calls this after the same step: if any got SIGTERM, all stop after this step."""
        if trainer.world_size <= 1:
            return
        flag = torch.tensor([float(self.received)], device=trainer.strategy.root_device)
        torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
        if flag.item() > 0:
            trainer._signal_connector.received_sigterm = True  # Lightning stops at the end of this step
