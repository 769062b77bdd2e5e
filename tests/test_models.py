from functools import partial

import pytest
import torch

from otgb.models import ConditionalMLP, GreyBoxODE, MLPCritic
from otgb.physics import SimulationDiverged


def _greybox(physics, z_dim=0, **kw):
    return GreyBoxODE(physics, z_dim, partial(ConditionalMLP, **kw))


def test_zero_correction_reproduces_fp(pendulum, generator):
    gb = _greybox(pendulum, output_scale=0.0)
    x0, theta = pendulum.sample_initial_state(5, generator), pendulum.sample_theta(5, generator)
    x = pendulum.simulate(x0, theta)
    assert torch.allclose(gb(x, x0, theta, torch.zeros(5, 0)), x, atol=1e-6)


def test_exact_correction_reproduces_the_dgp(pendulum, damped, generator):
    class Friction(torch.nn.Module):
        def forward(self, state, cond):
            return -1.2 * state[:, 1:2]

    gb = GreyBoxODE(pendulum, 0, lambda *shapes: Friction())
    x0, theta = pendulum.sample_initial_state(5, generator), pendulum.sample_theta(5, generator)
    y = damped.simulate(x0, theta, torch.full((5, 1), 1.2))
    assert torch.allclose(gb(None, x0, theta, torch.zeros(5, 0)), y, atol=1e-5)
    parts = gb.components(x0, theta, torch.zeros(5, 0))
    assert parts["physics"].shape == (5, 50, 2) and parts["correction"].shape == (5, 50, 1)
    assert torch.allclose(parts["correction"][..., 0], -1.2 * parts["states"][..., 1])
    field = damped.vector_field(parts["states"].flatten(0, 1), theta.repeat_interleave(50, 0), torch.full((250, 1), 1.2))
    total = parts["physics"].clone()
    total[..., 1] += parts["correction"][..., 0]
    assert torch.allclose(total.flatten(0, 1), field, atol=1e-6)


def test_correction_starts_small_and_uses_z(pendulum, generator):
    gb = _greybox(pendulum, z_dim=3, output_scale=0.01)
    state, cond = torch.randn(64, 2), torch.randn(64, 4)
    assert gb.correction(state, cond).abs().max() < 0.05
    assert not torch.allclose(gb.correction(state, cond), gb.correction(state, torch.randn(64, 4)))


def test_critic_maps_trajectories_to_scalars():
    critic = MLPCritic((50, 1))
    assert critic(torch.randn(7, 50, 1)).shape == (7,)


def test_diverging_greybox_solve_is_named(pendulum, generator):
    class Exploding(torch.nn.Module):
        def forward(self, state, cond):
            return torch.exp(50 * state[:, 1:2].abs())

    gb = GreyBoxODE(pendulum, 0, lambda *shapes: Exploding())
    x0, theta = pendulum.sample_initial_state(3, generator), pendulum.sample_theta(3, generator)
    with pytest.raises(SimulationDiverged, match="GreyBoxODE: the solve produced NaN/Inf"):
        gb(None, x0, theta, torch.zeros(3, 0))
