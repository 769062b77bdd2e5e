from functools import partial

import pytest
import torch

from otgb.callbacks import FieldFigure
from otgb.errors import InputError
from otgb.models import ConditionalConvNet, ConditionalMLP, ConvCritic, GreyBoxODE, MLPCritic, SeparableCorrection
from otgb.ot import critic_loss
from otgb.physics import Constant, FitzHughNagumoReaction, ReactionDiffusion, SimulationDiverged


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


def test_separable_correction_moves_the_state_only_along_its_basis():
    basis = partial(ConditionalConvNet, channels=(8,), padding_mode="zeros", output_scale=1.0)
    correction = SeparableCorrection((1, 20), (1, 20), 5, basis, rank=2)
    u = torch.randn(1, 1, 20).expand(64, -1, -1)
    draws = correction(u, torch.randn(64, 5)).flatten(1)  # one state, 64 conditions
    assert torch.linalg.matrix_rank(draws).item() == 2  # every draw is a mix of the same 2 fields
    free = ConditionalConvNet((1, 20), (1, 20), 5, channels=(8,), output_scale=1.0)
    assert torch.linalg.matrix_rank(free(u, torch.randn(64, 5)).flatten(1)).item() > 2


def test_separable_correction_in_a_greybox_keeps_f_p_shapes(pendulum, generator):
    gb = GreyBoxODE(pendulum, 3, partial(SeparableCorrection, basis=partial(ConditionalMLP, hidden=(16,)), rank=1))
    x0, theta = pendulum.sample_initial_state(4, generator), pendulum.sample_theta(4, generator)
    assert gb(None, x0, theta, torch.randn(4, 3)).shape == (4, 50, 1)


def test_separable_correction_needs_a_condition_and_a_rank():
    with pytest.raises(InputError, match="SeparableCorrection needs rank >= 1 and a condition"):
        SeparableCorrection((2,), (1,), 0, partial(ConditionalMLP))
    with pytest.raises(InputError, match="got rank=0"):
        SeparableCorrection((2,), (1,), 3, partial(ConditionalMLP), rank=0)


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


def test_conv_correction_on_a_periodic_grid_commutes_with_shifts(generator):
    net = ConditionalConvNet((2, 16, 16), (2, 16, 16), cond_dim=4, padding_mode="circular", output_scale=1.0)
    u, cond = torch.randn(3, 2, 16, 16, generator=generator), torch.randn(3, 4, generator=generator)
    shifted = net(torch.roll(u, (3, -5), (-2, -1)), cond)
    assert torch.allclose(shifted, torch.roll(net(u, cond), (3, -5), (-2, -1)), atol=1e-5)
    assert not torch.allclose(net(u, cond), net(u, torch.randn(3, 4, generator=generator))), "the condition is used"
    small = ConditionalConvNet((1, 20), (1, 20), cond_dim=1, output_scale=0.01)
    assert small(torch.randn(5, 1, 20), torch.randn(5, 1)).abs().max() < 0.05


def test_greybox_with_the_missing_reaction_reproduces_the_dgp(generator):
    physics = ReactionDiffusion(n_grid=8)
    dgp = physics.with_hidden_effect([FitzHughNagumoReaction(Constant(5e-3))])

    class Reaction(torch.nn.Module):
        def forward(self, state, cond):
            u, v = state[:, 0], state[:, 1]
            return torch.stack([u - u**3 - v - 5e-3, torch.zeros_like(v)], dim=1)

    x0, theta = physics.sample_initial_state(3, generator), physics.sample_theta(3, generator)
    y = dgp.simulate(x0, theta, torch.full((3, 1), 5e-3))
    assert torch.allclose(GreyBoxODE(physics, 0, lambda *shapes: Reaction())(None, x0, theta, torch.zeros(3, 0)), y, atol=1e-5)
    zero = GreyBoxODE(physics, 2, partial(ConditionalConvNet, padding_mode="circular", output_scale=0.0))
    assert torch.allclose(zero(None, x0, theta, torch.randn(3, 2)), physics.simulate(x0, theta), atol=1e-6)


@pytest.mark.parametrize("time_as_channels", [True, False])
def test_conv_critic_scores_trajectories_and_takes_a_gradient_penalty(time_as_channels, generator):
    shape = (6, 2, 8, 8)
    critic = ConvCritic(shape, channels=(8, 16), time_as_channels=time_as_channels)
    real, fake = torch.randn(4, *shape, generator=generator), torch.randn(4, *shape, generator=generator)
    scores = critic(torch.cat([real, fake]))
    assert scores.shape == (8,) and torch.allclose(scores[:4], critic(real), atol=1e-6), "one score per trajectory"
    loss, parts = critic_loss(critic, real, fake, gp_weight=1.0, generator=generator)
    loss.backward()
    assert parts["gradient_penalty"] > 0 and all(p.grad is not None for p in critic.parameters())


def test_a_bf16_critic_scores_as_the_float32_one_to_bf16_rounding_and_trains_with_a_gradient_penalty(generator):
    shape = (6, 2, 8, 8)
    full = ConvCritic(shape, channels=(8, 16))
    mixed = ConvCritic(shape, channels=(8, 16), precision="bf16-mixed")
    mixed.load_state_dict(full.state_dict())  # the same float32 weights: the checkpoints are interchangeable
    real, fake = torch.randn(4, *shape, generator=generator), torch.randn(4, *shape, generator=generator)
    scores, rounded = full(real), mixed(real)
    assert rounded.dtype == torch.float32 and not torch.equal(scores, rounded), "the convolutions ran in bfloat16"
    assert torch.allclose(rounded, scores, rtol=0.02, atol=0.02 * scores.abs().max().item())
    loss, parts = critic_loss(mixed, real, fake, gp_weight=1.0, generator=generator)
    loss.backward()
    assert torch.isfinite(loss) and parts["gradient_penalty"] > 0
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in mixed.parameters())
    with pytest.raises(InputError, match=r"model.critic.init_args.precision: 'fp16' is not one of \('32-true', 'bf16-mixed'\)"):
        ConvCritic(shape, precision="fp16")


def test_field_figure_names_a_missing_channel(generator):
    physics = ReactionDiffusion(n_grid=8)
    x = torch.rand(1, 15, 2, 8, 8, generator=generator)
    data = {"x": x, "y": x[:, None], "theta": physics.sample_theta(1, generator)}
    with pytest.raises(ValueError, match="FieldFigure.channel=2: the observed field has 2 channel"):
        FieldFigure(n_inputs=1, channel=2).draw(data, x[:, None], physics, step=0)
    figure = FieldFigure(n_inputs=1, channel=1).draw(data, x[:, None], physics, step=0)
    assert len([ax for ax in figure.axes if ax.images]) == 3 * 4, "measured, generated and f_p at four frames"


def _concatenated_forward(net, u, cond):
    """The conditional networks as their docstrings define them: each layer sees [h, code(cond)]."""
    code = net.encoder(cond)
    h = u.flatten(1) if isinstance(net, ConditionalMLP) else u
    layers = [*net.hidden, net.out] if isinstance(net, ConditionalMLP) else list(net.layers)
    for i, layer in enumerate(layers):
        spread = code.reshape(*code.shape, *([1] * (h.dim() - 2))).expand(-1, -1, *h.shape[2:])
        h = layer(torch.cat([h, spread], dim=1))
        h = net.act(h) if i < len(layers) - 1 else h
    return h.reshape(len(u), *net.out_shape) if isinstance(net, ConditionalMLP) else h


@pytest.mark.parametrize(
    "net, shape",
    [
        (ConditionalMLP((2,), (1,), 3, output_scale=1.0), (5, 2)),
        (ConditionalConvNet((1, 9), (1, 9), 3, padding_mode="zeros", output_scale=1.0), (5, 1, 9)),
        (ConditionalConvNet((2, 6, 6), (2, 6, 6), 3, padding_mode="circular", output_scale=1.0), (5, 2, 6, 6)),
    ],
    ids=["mlp", "conv1d-zeros", "conv2d-circular"],
)
def test_the_condition_computed_once_per_solve_gives_the_concatenated_networks(net, shape, generator):
    u, cond = torch.randn(shape, generator=generator), torch.randn(shape[0], 3, generator=generator)
    parts = net.condition(cond)
    assert torch.allclose(net.conditioned(u, *parts), _concatenated_forward(net, u, cond), atol=1e-6)
    assert torch.allclose(net(u, cond), _concatenated_forward(net, u, cond), atol=1e-6)


@pytest.mark.parametrize(
    ("padding_mode", "kernel_size", "compiled"),
    [("zeros", 3, True), ("circular", 3, False), ("reflect", 3, False), ("replicate", 3, False), ("zeros", 5, False)],
)
def test_a_compiled_1d_convolution_equals_the_library_s_values_and_gradients(padding_mode, kernel_size, compiled, monkeypatch):
    """Inside a compiled solve a 1-D convolution runs grid-major, as shifted views and one matrix product: the same numbers.
    One case goes through torch.compile; the others run the grid-major code eagerly (a compile costs ~10 s each)."""
    torch.manual_seed(0)
    net = ConditionalConvNet((1, 20), (1, 20), 3, channels=(16, 16), kernel_size=kernel_size, padding_mode=padding_mode)
    u, cond = torch.randn(8, 1, 20, requires_grad=True), torch.randn(8, 3)

    def values_and_gradients(conditioned):
        out = conditioned(u, *net.condition(cond))
        return [out, *torch.autograd.grad(out.square().sum(), [u, *net.parameters()])]

    eager = values_and_gradients(net.conditioned)
    if compiled:
        grid_major = values_and_gradients(torch.compile(net.conditioned, fullgraph=True))
    else:
        monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)
        grid_major = values_and_gradients(net.conditioned)
    for a, b in zip(eager, grid_major):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6 * float(a.detach().abs().max()))
