"""Kernel weak optimal-transport cost (paper eq. kernel-cost and its estimator, App. D).

For a source sample x and |Z| outputs T_x(z_1..z_|Z|) of the map, the unbiased estimator is

    C_hat = 1/2 k(x, x) + (1 - gamma)/(2|Z|) sum_z k(T(z), T(z)) - 1/|Z| sum_z k(x, T(z))
            + gamma / (2|Z|(|Z|-1)) sum_{z != z'} k(T(z), T(z'))

(Korotin et al. 2023, "Kernel neural optimal transport"). With the distance kernel
k(a, b) = -||a - b|| / 2 (Frobenius norm over all non-batch dimensions) the diagonal terms
vanish and

    C_hat = 1/(2|Z|) sum_z ||x - T(z)|| - gamma / (4|Z|(|Z|-1)) sum_{z != z'} ||T(z) - T(z')||,

i.e. half the mean transport distance minus a quarter of the mean spread between outputs.
With |Z| = 1 (one-to-one) only the transport term is left.
"""

from __future__ import annotations

from torch import Tensor


def pairwise_distance(a: Tensor, b: Tensor) -> Tensor:
    """||a_i - b_j|| over all trailing dims: a (B, I, ...), b (B, J, ...) -> (B, I, J)."""
    return (a.flatten(2).unsqueeze(2) - b.flatten(2).unsqueeze(1)).norm(dim=-1)


def distance_kernel_weak_cost(x: Tensor, y: Tensor, gamma: float) -> Tensor:
    """Estimator of C_{k,gamma}(x, T_x#eta) with the distance kernel, per source sample.

    Args:
        x: source trajectories, (B, *traj).
        y: map outputs for |Z| latent draws per source, (B, Z, *traj).
        gamma: weight of the variance term in [0, 1]; gamma > 0 needs Z >= 2.

    Returns:
        (B,) cost per source sample.
    """
    n_z = y.shape[1]
    if gamma > 0 and n_z < 2:
        raise ValueError(f"the variance term (gamma={gamma}) needs at least 2 latent draws per source, got {n_z}")
    transport = (y.flatten(2) - x.flatten(1).unsqueeze(1)).norm(dim=-1).mean(dim=1) / 2
    if gamma == 0:
        return transport
    spread = pairwise_distance(y, y).sum(dim=(1, 2)) / (n_z * (n_z - 1))
    return transport - gamma * spread / 4
