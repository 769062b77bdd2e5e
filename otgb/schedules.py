"""Learning-rate schedules that know the length of the run."""

from __future__ import annotations

import math

from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR

from otgb.errors import InputError


class CosineOverRun(LambdaLR):
    """Cosine decay from the initial learning rate to ``final_factor`` times it.

    ``total_steps`` defaults to the run's length in training steps, which :class:`MapTraining`
    fills in from the trainer (the simulation budget or ``max_steps``, whichever ends first),
    so the schedule follows a changed budget without editing the config.

    Args:
        optimizer: the optimiser whose learning rate is scheduled.
        final_factor: the learning rate at the end of the run, as a fraction of the initial one.
        total_steps: length of the run in training steps (None: filled in by the module; no
            decay until then).
    """

    def __init__(self, optimizer: Optimizer, final_factor: float = 0.01, total_steps: int | None = None) -> None:
        if not 0.0 <= final_factor <= 1.0:
            raise ValueError(f"CosineOverRun.final_factor={final_factor}: expected a value in [0, 1]")
        self.final_factor, self.total_steps = final_factor, total_steps
        super().__init__(optimizer, self.factor)

    def factor(self, step: int) -> float:
        if not self.total_steps:
            return 1.0
        progress = min(step / self.total_steps, 1.0)
        return self.final_factor + (1 - self.final_factor) * 0.5 * (1 + math.cos(math.pi * progress))


class BatchScaledRate:
    """Learning rates that follow the batch: the rates in the config were tuned at ``reference_batch``, and a run with
    batch b trains with ``lr * (b / reference_batch) ** exponent``.

    The rule and its default exponent come from runs of Pendulum-1-m at 1e6 simulations and batch 320, against
    several exponents (docs/results.md, "Budget and batch"): the adversarial game wants a *smaller* step as the batch
    grows; the square-root rule of supervised learning, which raises it, made the map worse. A scaled rate outside
    ``[min_lr, max_lr]`` is refused rather than trained with: above the default ``max_lr`` the pendulum's map
    trained worse at batch 32 and at batch 320.

    Args:
        reference_batch: the batch at which the configured learning rates were chosen.
        exponent: the power of ``b / reference_batch`` applied to each learning rate.
        min_lr: the smallest learning rate the rule may give.
        max_lr: the largest learning rate the rule may give.
    """

    def __init__(self, reference_batch: int = 32, exponent: float = -0.3, min_lr: float = 1e-5, max_lr: float = 2e-3) -> None:
        if reference_batch < 1 or not 0 < min_lr < max_lr:
            raise InputError(
                "model.lr_batch_rule: need reference_batch >= 1 and 0 < min_lr < max_lr; "
                f"got {reference_batch}, {min_lr}, {max_lr}"
            )
        self.reference_batch, self.exponent, self.min_lr, self.max_lr = reference_batch, exponent, min_lr, max_lr

    def apply(self, optimizer: Optimizer, batch: int, name: str) -> None:
        """Scale ``optimizer``'s learning rates for ``batch`` (before any schedule is built on them)."""
        factor = (batch / self.reference_batch) ** self.exponent
        for group in optimizer.param_groups:
            lr = group["lr"] * factor
            if not self.min_lr <= lr <= self.max_lr:
                raise InputError(
                    f"model.lr_batch_rule: {name}'s learning rate {group['lr']:g} scaled to batch {batch} is {lr:.3g}, "
                    f"outside the stable range [{self.min_lr:g}, {self.max_lr:g}]; choose data.batch_size closer to "
                    f"{self.reference_batch} or a learning rate for it"
                )
            group["lr"] = lr
