"""Learning-rate schedules that know the length of the run."""

from __future__ import annotations

import math

from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR


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
