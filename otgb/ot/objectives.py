"""What the map minimises against the critic: the objective, one class each, chosen by ``model.objective``.

- :class:`WeakTransport` (otgb's method): the kernel weak OT maximin (paper eq. kernel-maximin),
  L_T = mean_x [ C_hat_{k,gamma}(x, T_x(Z)) - mean_z f(T_x(z)) ].
- :class:`WassersteinGAN` (the paper's WGAN-GP baseline): L_T = -mean f(T(x)), no transport
  cost, so nothing ties an output to its input (Gulrajani et al. 2017, "Improved Training of
  Wasserstein GANs").

Both share the critic's loss (:func:`otgb.ot.critic_loss`: mean f(y_hat) - mean f(y) + lambda GP).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from otgb.errors import InputError
from otgb.ot.costs import KERNELS, kernel_weak_cost


class Objective(ABC):
    """The map's loss for outputs ``y_hat`` (B, |Z|, T, *obs) of sources ``x`` (B, T, *obs) under ``critic``."""

    @abstractmethod
    def map_loss(self, x: Tensor, y_hat: Tensor, critic: nn.Module) -> tuple[Tensor, dict[str, Tensor]]:
        """The loss to minimise and its parts for logging (``map_loss`` and what it is made of)."""

    def check_draws(self, n_z: int) -> None:  # noqa: B027 (most objectives work with any number of draws)
        """Raise :class:`InputError` if the objective cannot work with ``n_z`` latent draws per source."""


class WeakTransport(Objective):
    """Kernel weak OT: the transport cost C_hat_{k,gamma} (:func:`otgb.ot.kernel_weak_cost`) minus the critic.

    Args:
        gamma: weight of the variance term of the weak cost (0 one-to-one, 1 one-to-many).
        kernel: kernel of the weak cost, "distance" (-||a - b|| / 2, the paper's) or "linear"
            (<a, b> / D: the weak quadratic cost, half the mean squared error one-to-one).
        cost_weight: the transport cost's weight against the critic (1: the paper's maximin);
            below 1 the cost pulls the map's outputs less towards f_p's, above 1 more.
    """

    def __init__(self, gamma: float = 0.0, kernel: str = "distance", cost_weight: float = 1.0) -> None:
        if not 0.0 <= gamma <= 1.0:
            raise InputError(f"model.objective.gamma={gamma}: expected a value in [0, 1]")
        if kernel not in KERNELS:
            raise InputError(f"model.objective.kernel={kernel!r}: expected one of {sorted(KERNELS)}")
        if not cost_weight > 0:
            raise InputError(f"model.objective.cost_weight={cost_weight}: expected a value > 0")
        self.gamma, self.kernel_name, self.kernel, self.cost_weight = gamma, kernel, KERNELS[kernel], cost_weight

    def check_draws(self, n_z: int) -> None:
        if self.gamma > 0 and n_z < 2:
            raise InputError(f"model.objective.gamma={self.gamma} > 0 needs n_z >= 2 latent draws per source (got n_z={n_z})")

    def map_loss(self, x: Tensor, y_hat: Tensor, critic: nn.Module) -> tuple[Tensor, dict[str, Tensor]]:
        cost = kernel_weak_cost(x, y_hat, self.gamma, self.kernel).mean()
        loss = self.cost_weight * cost - critic(y_hat.flatten(0, 1)).mean()
        return loss, {"map_loss": loss.detach(), "transport_cost": cost.detach()}

    def __repr__(self) -> str:
        return f"WeakTransport(gamma={self.gamma}, kernel={self.kernel_name!r}, cost_weight={self.cost_weight})"


class WassersteinGAN(Objective):
    """WGAN-GP's generator loss -mean f(T(x)): the map only has to fool the critic."""

    def map_loss(self, x: Tensor, y_hat: Tensor, critic: nn.Module) -> tuple[Tensor, dict[str, Tensor]]:
        loss = -critic(y_hat.flatten(0, 1)).mean()
        return loss, {"map_loss": loss.detach()}

    def __repr__(self) -> str:
        return "WassersteinGAN()"
