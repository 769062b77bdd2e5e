"""Transport costs and critic objectives."""

from otgb.ot.costs import KERNELS, distance_kernel, kernel_weak_cost, linear_kernel
from otgb.ot.penalty import critic_loss, gradient_penalty

__all__ = ["KERNELS", "critic_loss", "distance_kernel", "gradient_penalty", "kernel_weak_cost", "linear_kernel"]
