"""Transport costs and critic objectives."""

from otgb.ot.costs import distance_kernel_weak_cost, pairwise_distance
from otgb.ot.penalty import critic_loss, gradient_penalty

__all__ = ["critic_loss", "distance_kernel_weak_cost", "gradient_penalty", "pairwise_distance"]
