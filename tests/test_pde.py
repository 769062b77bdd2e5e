"""The PDE systems: advection-diffusion and FitzHugh-Nagumo reaction-diffusion."""

import math

import pytest
import torch
import torch.nn.functional as F

from otgb.errors import InputError
from otgb.physics import (
    Advection,
    AdvectionDiffusion,
    Constant,
    ConstantDrain,
    FieldModel,
    FitzHughNagumoReaction,
    LibraryTerm,
    Pendulum,
    Prior,
    ReactionDiffusion,
)


def test_advection_diffusion_shapes_and_initial_profile(generator):
    model = AdvectionDiffusion()
    x0, theta = model.sample_initial_state(6, generator), model.sample_theta(6, generator)
    x = model.simulate(x0, theta)
    assert x.shape == (6, 50, 1, 20) == (6, *model.trajectory_shape)
    assert torch.allclose(model.grid[[0, -1]], torch.tensor([0.1, 2.0]))
    amplitude = x0[:, 0, 9] / math.sin(math.pi * 1.0 / 2)
    assert torch.allclose(x0[:, 0], amplitude[:, None] * torch.sin(math.pi * model.grid / 2), atol=1e-6)
    assert ((amplitude >= 0.5) & (amplitude <= 1.5)).all() and torch.equal(x[:, 0], x0)
    assert torch.allclose(model.times()[[1, -1]], torch.tensor([0.02, 0.98]))


def test_pure_diffusion_decays_like_the_heat_equations_sine_mode():
    """On [0, L] with zero ends, sin(pi s / L) decays as exp(-alpha (pi / L)^2 t)."""
    model = AdvectionDiffusion(n_grid=49, dx=0.04, dt=0.1, n_obs=11, step_size=0.01)
    length = (model.n_grid + 1) * model.dx
    alpha = 0.05
    x0 = torch.sin(math.pi * model.grid / length).reshape(1, 1, -1).double()
    x = model.solve(model.field, x0, torch.tensor([[alpha]], dtype=torch.float64))
    amplitude = (x[0, :, 0] * x0[0, 0]).sum(-1) / (x0[0, 0] ** 2).sum()
    expected = torch.exp(-alpha * (math.pi / length) ** 2 * model.times().double())
    assert torch.allclose(amplitude, expected, rtol=2e-3)
    shape_kept = x[0, -1, 0] / amplitude[-1]
    assert torch.allclose(shape_kept, x0[0, 0], atol=1e-6), "a sine mode keeps its shape"


def test_advection_moves_the_profile_at_speed_beta():
    model = AdvectionDiffusion(n_grid=199, dx=0.01, dt=0.1, n_obs=6, step_size=0.005)
    beta = 0.6
    dgp = model.with_hidden_effect([Advection(Constant(beta))])
    s = model.grid
    x0 = torch.exp(-(((s - 0.6) / 0.08) ** 2)).reshape(1, 1, -1)
    y = dgp.simulate(x0, torch.zeros(1, 1), torch.full((1, 1), beta))[0, :, 0]
    centre = (y * s).sum(-1) / y.sum(-1)
    assert torch.allclose(centre - centre[0], beta * model.times(), atol=2e-3)
    assert torch.allclose(y.sum(-1), y[0].sum(), rtol=1e-4), "mass is conserved away from the ends"


def test_spatial_terms_need_a_field_model():
    message = "Advection acts on an otgb.physics.FieldModel; Pendulum is not one"
    with pytest.raises(InputError, match=message):
        Pendulum().with_hidden_effect([Advection(Constant(0.1))])
    with pytest.raises(InputError, match=message):
        Pendulum(hidden_effect=[Advection(Constant(0.1))])
    with pytest.raises(InputError, match=r"ConstantDrain: channel=2 is invalid; expected an index 0..1 into .*\('u', 'v'\)"):
        ReactionDiffusion(n_grid=8).with_hidden_effect([ConstantDrain(Constant(1.0), channel=2)])
    with pytest.raises(InputError, match="FitzHughNagumoReaction acts on a \\(u, v\\) state; AdvectionDiffusion has"):
        AdvectionDiffusion().with_hidden_effect([FitzHughNagumoReaction(Constant(1.0))])


class Heat(FieldModel):
    """Diffusion alpha Lap(T) of one channel on any grid (the FieldModel contract in a few lines)."""

    state_names = ("T",)
    theta_names = ("alpha",)

    def __init__(self, grid_shape=(8, 8), dx=0.1, boundary="periodic", alpha: Prior = Constant(0.1)) -> None:
        super().__init__(grid_shape, dx, boundary, dt=0.1, n_obs=3)

    def field(self, state, theta):
        return theta[:, 0, None, None, None] * self.laplacian(state)

    def sample_initial_state(self, n, generator):
        return torch.rand(n, *self.state_shape, generator=generator)


def test_field_model_holds_a_validated_grid(generator):
    heat = Heat()
    assert heat.state_shape == heat.obs_shape == (1, 8, 8) and heat.spatial_dims == 2 and heat.boundary == "periodic"
    x0 = heat.sample_initial_state(2, generator)
    y = heat.simulate(x0, heat.sample_theta(2, generator))
    assert y.shape == (2, 3, 1, 8, 8) and torch.allclose(y.mean((-2, -1)), x0.mean((-2, -1), keepdim=True).squeeze(-1))
    for kwargs, message in [
        ({"grid_shape": (8, 2)}, r"Heat: grid_shape=\(8, 2\) is invalid; expected one integer >= 3 per spatial axis"),
        ({"grid_shape": ()}, r"grid_shape=\(\) is invalid"),
        ({"dx": 0.0}, "Heat: dx=0.0 is invalid; expected a positive number"),
        ({"boundary": "neumann"}, "Heat: boundary='neumann' is invalid; expected one of 'dirichlet', 'periodic'"),
    ]:
        with pytest.raises(InputError, match=message):
            Heat(**kwargs)
    with pytest.raises(InputError, match="AdvectionDiffusion: n_grid=2 is invalid; expected an integer >= 3"):
        AdvectionDiffusion(n_grid=2)
    with pytest.raises(InputError, match="ReactionDiffusion: u_reaction='yes' is invalid"):
        ReactionDiffusion(u_reaction="yes")
    with pytest.raises(InputError, match="AdvectionDiffusion: amplitude=1.0 is invalid; expected a Prior"):
        AdvectionDiffusion(amplitude=1.0)


def _periodic_laplacian(u, dx):
    kernel = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]]).reshape(1, 1, 3, 3) / dx**2
    flat = u.reshape(-1, 1, *u.shape[-2:])
    return F.conv2d(F.pad(flat, (1, 1, 1, 1), mode="circular"), kernel).reshape(u.shape)


@pytest.mark.parametrize("u_reaction", [False, True])
def test_reaction_diffusion_field_matches_a_direct_evaluation(u_reaction, generator):
    model = ReactionDiffusion(u_reaction=u_reaction, n_grid=16)
    state, theta = torch.randn(3, 2, 16, 16, generator=generator), model.sample_theta(3, generator)
    u, v = state[:, 0], state[:, 1]
    lap = _periodic_laplacian(state, 2 / 16)
    a, b = theta[:, 0, None, None], theta[:, 1, None, None]
    du = a * lap[:, 0] + (u - u**3 - v if u_reaction else 0)
    dv = b * lap[:, 1] + u - v
    assert torch.allclose(model.field(state, theta), torch.stack([du, dv], 1), atol=1e-4)


def test_hidden_reaction_terms_match_a_direct_evaluation(generator):
    state = torch.randn(3, 2, 8, 8, generator=generator)
    u, v = state[:, 0], state[:, 1]
    k = torch.tensor([[1e-3], [5e-3], [2e-2]])
    model = ReactionDiffusion(n_grid=8)
    reaction = FitzHughNagumoReaction(Constant(5e-3))(state, k, model)
    assert torch.allclose(reaction[:, 0], u - u**3 - v - k[:, :, None]) and (reaction[:, 1] == 0).all()
    drain = ConstantDrain(Constant(5e-3))(state, k, model)
    assert torch.allclose(drain[:, 0], -k[:, :, None].expand(3, 8, 8)) and (drain[:, 1] == 0).all()
    full = model.with_hidden_effect([FitzHughNagumoReaction(Constant(5e-3))])
    known = ReactionDiffusion(n_grid=8, u_reaction=True).with_hidden_effect([ConstantDrain(Constant(5e-3))])
    theta = model.sample_theta(3, generator)
    assert torch.allclose(full.vector_field(state, theta, k), known.vector_field(state, theta, k), atol=1e-5)


def test_periodic_boundaries_wrap(generator):
    model = ReactionDiffusion(n_grid=16)
    theta = torch.tensor([[2e-3, 5e-3]])
    bump = torch.zeros(1, 2, 16, 16)
    bump[:, :, 0, 0] = 1.0
    y = model.simulate(bump, theta)[0, 0, 0]
    assert y[15, 0] > 1e-3 and torch.isclose(y[15, 0], y[1, 0]) and torch.isclose(y[0, 15], y[0, 1])
    x0 = torch.rand(1, 2, 16, 16, generator=generator)
    rolled = model.simulate(torch.roll(x0, (5, -3), (-2, -1)), theta)
    assert torch.allclose(rolled, torch.roll(model.simulate(x0, theta), (5, -3), (-2, -1)), atol=1e-6)


def test_reaction_diffusion_shapes_frames_and_measured_step(generator):
    model = ReactionDiffusion()
    x0, theta = model.sample_initial_state(4, generator), model.sample_theta(4, generator)
    x = model.simulate(x0, theta)
    assert x.shape == (4, 15, 2, 32, 32) == (4, *model.trajectory_shape)
    assert ((x0 >= 0) & (x0 <= 1)).all() and ((theta[:, 0] >= 1e-3) & (theta[:, 1] <= 7e-3)).all()
    assert torch.allclose(model.times()[1:][[0, -1]], torch.tensor([0.1, 1.5])), "frames at t = 0.1 ... 1.5"
    term = [FitzHughNagumoReaction(Constant(5e-3))]
    k = torch.full((4, 1), 5e-3)
    fine = model.with_hidden_effect(term, step_size=1e-3).simulate(x0, theta, k)
    coarse = model.with_hidden_effect(term, step_size=1e-2).simulate(x0, theta, k)
    assert (fine - coarse).abs().max() < 1e-5, "the measured data's RK4 step is converged"


def test_the_scipy_rod_of_the_variation_benchmark_matches_otgbs_solve_with_the_same_decay(tmp_path):
    """scripts/scipy_advdiff.py (SciPy's DOP853 on the method of lines) against AdvectionDiffusion plus -k T (otgb's
    RK4): the two solvers agree far below the files' noise (sd 0.01), so a benchmark on those files measures discovery,
    not a difference of discretisations; each trajectory draws its own rate where asked."""
    import sys
    from pathlib import Path

    import numpy as np

    sys.path.insert(0, str(Path(__file__).parents[1] / "scripts"))
    import scipy_advdiff

    constant = np.load(scipy_advdiff.write(tmp_path / "rod.npz", 0.6, 0.0, 4, 3, 0.0))["y"]
    rng, draws = np.random.default_rng(3), []  # the script's draws, in its order: alpha, amplitude, then the noise
    for _ in range(4):
        draws.append((rng.uniform(0.01, 0.1), rng.uniform(0.5, 1.5)))
        rng.normal(0, 0.0, (50, 20))
    model = AdvectionDiffusion().with_hidden_effect([LibraryTerm("T", "T", Constant(-0.6))])
    profile = torch.sin(math.pi * model.grid / 2)
    x0 = torch.stack([a * profile for _, a in draws]).unsqueeze(1)
    theta = torch.tensor([[alpha] for alpha, _ in draws])
    solved = model.simulate(x0, theta, model.sample_effect_params(4, torch.Generator().manual_seed(0)))
    assert constant.shape == (4, 50, 1, 20)
    assert float((solved - torch.from_numpy(constant)).abs().max()) < 1e-4
    varying = np.load(scipy_advdiff.write(tmp_path / "varying.npz", 0.6, 0.3, 4, 3, 0.0))["y"]
    late = varying[:, -1, 0].sum(1) / constant[:, -1, 0].sum(1)  # the last frame's heat against the constant rate's
    assert late.std() > 0.01, late
