"""Critic objective of the maximin (paper eq. kernel-maximin, Algorithm 1) with WGAN-GP."""

from __future__ import annotations

import torch
from torch import Tensor, nn


def gradient_penalty(
    critic: nn.Module, real: Tensor, fake: Tensor, generator: torch.Generator | None = None, one_sided: bool = False
) -> Tensor:
    """E[(||grad f(y~)||_2 - 1)^2] on y~ = eps y + (1 - eps) y_hat, eps ~ U(0, 1) per sample.

    The norm is taken once per sample over all non-batch dimensions (Gulrajani et al. 2017).
    ``real`` and ``fake`` are paired row by row: both (N, *traj). ``generator`` (on their
    device) draws eps. ``one_sided`` penalises only norms above 1, E[max(0, ||grad f|| - 1)^2]
    (Petzka et al. 2018, "On the regularization of Wasserstein GANs"): the critic stays
    1-Lipschitz but may be flat where the two samples already agree.
    """
    if real.shape != fake.shape:
        raise ValueError(f"gradient_penalty pairs samples row by row: real {tuple(real.shape)} vs fake {tuple(fake.shape)}")
    eps_shape = (real.shape[0],) + (1,) * (real.dim() - 1)
    eps = torch.rand(eps_shape, generator=generator, device=real.device, dtype=real.dtype)
    mixed = (eps * real + (1 - eps) * fake).detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(critic(mixed).sum(), mixed, create_graph=True)
    excess = grad.flatten(1).norm(dim=1) - 1
    return (excess.clamp(min=0) if one_sided else excess).pow(2).mean()


def critic_loss(
    critic: nn.Module,
    real: Tensor,
    fake: Tensor,
    gp_weight: float,
    generator: torch.Generator | None = None,
    one_sided: bool = False,
) -> tuple[Tensor, dict[str, Tensor]]:
    """mean f(y_hat) - mean f(y) + lambda * GP; returns the loss and its parts for logging.

    ``fake`` may hold more samples than ``real``: the penalty pairs the first
    min(len(real), len(fake)) of each (both batches are already in random order).
    ``one_sided``: the penalty's form (:func:`gradient_penalty`).
    """
    f_real, f_fake = critic(real).mean(), critic(fake).mean()
    n = min(len(real), len(fake))
    penalty = gradient_penalty(critic, real[:n], fake[:n], generator, one_sided) if gp_weight > 0 else real.new_zeros(())
    loss = f_fake - f_real + gp_weight * penalty
    return loss, {"critic_gap": f_real - f_fake, "gradient_penalty": penalty}
