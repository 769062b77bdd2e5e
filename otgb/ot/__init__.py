"""Transport costs, the map's objectives and the critic's objective."""

from otgb.ot.costs import KERNELS, distance_kernel, kernel_weak_cost, linear_kernel
from otgb.ot.objectives import Objective, WassersteinGAN, WeakTransport
from otgb.ot.penalty import critic_loss, gradient_penalty

__all__ = [
    "KERNELS",
    "Objective",
    "WassersteinGAN",
    "WeakTransport",
    "critic_loss",
    "distance_kernel",
    "gradient_penalty",
    "kernel_weak_cost",
    "linear_kernel",
]
