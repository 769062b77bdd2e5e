import math

import pytest
import torch
from torch import nn

from otgb.ot import critic_loss, gradient_penalty, kernel_weak_cost, linear_kernel


def test_one_to_one_cost_is_half_the_distance():
    x = torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    y = torch.tensor([[[3.0, 4.0]], [[1.0, 1.0]]])
    assert torch.allclose(kernel_weak_cost(x, y, gamma=0.0), torch.tensor([2.5, 0.0]))


def test_weak_cost_matches_the_kernel_estimator_by_hand():
    x = torch.tensor([[0.0, 0.0]])
    y = torch.tensor([[[3.0, 4.0], [0.0, 1.0], [0.0, -2.0]]])
    gamma = 0.7
    k = lambda a, b: -torch.dist(a, b) / 2  # noqa: E731
    zs = range(3)
    expected = (
        0.5 * k(x[0], x[0])
        + (1 - gamma) / (2 * 3) * sum(k(y[0, i], y[0, i]) for i in zs)
        - 1 / 3 * sum(k(x[0], y[0, i]) for i in zs)
        + gamma / (2 * 3 * 2) * sum(k(y[0, i], y[0, j]) for i in zs for j in zs if i != j)
    )
    # distances to x: 5, 1, 2; pairwise: |(3,3)|, |(3,6)|, 3
    by_hand = (5 + 1 + 2) / 6 - gamma * 2 * (math.sqrt(18) + math.sqrt(45) + 3) / (4 * 6)
    cost = kernel_weak_cost(x, y, gamma)
    assert torch.allclose(cost, expected.reshape(1)) and math.isclose(cost.item(), by_hand, rel_tol=1e-6)


def test_variance_term_needs_two_draws():
    with pytest.raises(ValueError, match="at least 2 latent draws"):
        kernel_weak_cost(torch.zeros(2, 3), torch.zeros(2, 1, 3), gamma=1.0)


class Linear(nn.Module):
    def __init__(self, weight):
        super().__init__()
        self.weight = nn.Parameter(weight)

    def forward(self, y):
        return (y.flatten(1) * self.weight).sum(1)


def test_gradient_penalty_uses_one_norm_per_sample_over_all_dims():
    # f(y) = <w, y> has gradient w everywhere: penalty (||w||_F - 1)^2 with the norm over (T, C).
    w = torch.tensor([[1.0, 2.0], [2.0, 4.0]])
    critic = Linear(w.flatten())
    real, fake = torch.randn(5, 2, 2), torch.randn(5, 2, 2)
    expected = (w.norm() - 1) ** 2  # = 16; a per-row norm would give ((sqrt5-1)^2 + (sqrt20-1)^2)/2
    assert torch.allclose(gradient_penalty(critic, real, fake), expected)


def test_the_one_sided_gradient_penalty_spares_a_critic_flatter_than_1_lipschitz():
    real, fake = torch.randn(5, 2, 2), torch.randn(5, 2, 2)
    flat = Linear(torch.tensor([0.3, 0.0, 0.4, 0.0]))  # gradient norm 0.5 everywhere
    steep = Linear(torch.tensor([1.2, 0.0, 1.6, 0.0]))  # gradient norm 2
    assert torch.allclose(gradient_penalty(flat, real, fake), torch.tensor(0.25))
    assert gradient_penalty(flat, real, fake, one_sided=True) == 0
    assert torch.allclose(gradient_penalty(steep, real, fake, one_sided=True), torch.tensor(1.0))
    _, parts = critic_loss(flat, real, fake, gp_weight=1.0, one_sided=True)
    assert parts["gradient_penalty"] == 0


def test_critic_loss_by_hand():
    critic = Linear(torch.tensor([0.6, 0.8]))  # unit gradient: no penalty
    real, fake = torch.tensor([[1.0, 0.0], [0.0, 1.0]]), torch.tensor([[0.0, 0.0], [1.0, 1.0], [2.0, 0.0]])
    loss, parts = critic_loss(critic, real, fake, gp_weight=10.0)
    f_real, f_fake = (0.6 + 0.8) / 2, (0 + 1.4 + 1.2) / 3
    assert torch.allclose(loss, torch.tensor(f_fake - f_real), atol=1e-6)
    assert torch.allclose(parts["critic_gap"], torch.tensor(f_real - f_fake))
    assert parts["gradient_penalty"].abs() < 1e-10


def test_linear_kernel_gives_the_weak_quadratic_cost():
    x, y = torch.randn(4, 5, 2), torch.randn(4, 3, 5, 2)
    one = kernel_weak_cost(x, y[:, :1], gamma=0.0, kernel=linear_kernel)
    assert torch.allclose(one, ((x - y[:, 0]) ** 2).flatten(1).mean(1) / 2, atol=1e-6)
    # eq. weak-ot-2 per dimension: mean_z ||x - y_z||^2 / (2D) - gamma/2 * Var_z(y) / D, with the unbiased variance
    gamma = 0.6
    d = 10
    spread = ((y - y.mean(1, keepdim=True)) ** 2).flatten(2).sum(-1).sum(1) / (3 - 1)
    expected = ((x.unsqueeze(1) - y) ** 2).flatten(2).sum(-1).mean(1) / (2 * d) - gamma * spread / (2 * d)
    assert torch.allclose(kernel_weak_cost(x, y, gamma, linear_kernel), expected, atol=1e-5)
