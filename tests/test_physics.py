import pytest
import torch

from otgb.errors import InputError
from otgb.physics import Choice, Constant, Pendulum, SimulationDiverged, Uniform, ViscousFriction


def _inputs(model, n, generator):
    return model.sample_initial_state(n, generator), model.sample_theta(n, generator)


def test_shapes_and_grid(pendulum, generator):
    x0, theta = _inputs(pendulum, 8, generator)
    x = pendulum.simulate(x0, theta)
    assert x.shape == (8, 50, 1) == (8, *pendulum.trajectory_shape)
    assert torch.allclose(pendulum.times()[[0, 1, -1]], torch.tensor([0.0, 0.1, 4.9]))
    assert torch.equal(x[:, 0, 0], x0[:, 0]), "the observed trajectory starts at the initial angle"
    assert (x0[:, 1] == 0).all() and (theta >= 0.785).all() and (theta <= 3.14).all()


def test_frictionless_pendulum_conserves_energy(pendulum, generator):
    x0, theta = _inputs(pendulum, 64, generator)
    states = pendulum.solve(pendulum.vector_field, x0.double(), theta)
    energy = pendulum.energy(states, theta.double())
    drift = (energy - energy[:, :1]).abs().max(dim=1).values / energy[:, 0].clamp_min(1e-3)
    assert drift.max() < 2e-3


def test_friction_decays_energy(damped, generator):
    x0, theta = _inputs(damped, 64, generator)
    effect = damped.sample_effect_params(64, generator)
    states = damped.solve(damped.vector_field, x0.double(), theta, effect)
    energy = damped.energy(states, theta.double())
    assert (energy[:, 1:] <= energy[:, :-1] + 1e-9).all()
    assert (energy[:, -1] < 0.01 * energy[:, 0]).all(), "xi = 1.2 over 4.9 s removes > 99% of the energy"


def test_rk4_matches_fine_reference_with_fourth_order_error(generator):
    coarse, half, fine = Pendulum(step_size=0.1), Pendulum(step_size=0.05), Pendulum(step_size=0.001)
    x0, theta = _inputs(coarse, 32, generator)
    x0, theta = x0.double(), theta.double()
    ref = fine.solve(fine.vector_field, x0, theta)
    err_coarse = (coarse.solve(coarse.vector_field, x0, theta) - ref).abs().max()
    err_half = (half.solve(half.vector_field, x0, theta) - ref).abs().max()
    assert err_coarse < 5e-3
    assert 10 < err_coarse / err_half < 24, "halving the step must cut the error ~16x (order 4)"


def test_hidden_effect_is_a_named_term_added_to_fp(pendulum, damped, generator):
    assert len(pendulum.terms) == 0 and not pendulum.is_stochastic
    assert isinstance(damped.terms[0], ViscousFriction) and damped.effect_dim == 1
    state, theta = torch.tensor([[0.3, -0.7]]), torch.tensor([[2.0]])
    diff = damped.vector_field(state, theta, torch.tensor([[1.2]])) - pendulum.vector_field(state, theta)
    assert torch.allclose(diff, torch.tensor([[0.0, 1.2 * 0.7]]))


def test_stochastic_priors(pendulum, generator):
    two = pendulum.with_hidden_effect([ViscousFriction(Choice([0.6, 1.5]))])
    many = pendulum.with_hidden_effect([ViscousFriction(Uniform(0.6, 1.5))])
    assert two.is_stochastic and many.is_stochastic
    assert torch.unique(two.sample_effect_params(200, generator)).tolist() == pytest.approx([0.6, 1.5])
    xi = many.sample_effect_params(1000, generator)
    assert xi.min() >= 0.6 and xi.max() <= 1.5 and 0.95 < xi.mean() < 1.15
    assert (Constant(1.2).sample(3, generator) == 1.2).all()


def test_bad_inputs_are_named(pendulum, damped):
    with pytest.raises(InputError, match="initial state has shape"):
        pendulum.simulate(torch.zeros(4, 3), torch.ones(4, 1))
    with pytest.raises(InputError, match="theta has shape"):
        pendulum.simulate(torch.zeros(4, 2), torch.ones(4, 2))
    with pytest.raises(InputError, match="hidden-effect parameters"):
        damped.simulate(torch.zeros(4, 2), torch.ones(4, 1))
    with pytest.raises(InputError, match=r"Pendulum: step_size=0.03 is invalid; expected a positive step that divides dt=0.1"):
        Pendulum(step_size=0.03)
    with pytest.raises(InputError, match="step_size=0.0 is invalid"):
        Pendulum(step_size=0.0)
    with pytest.raises(InputError, match=r"step_size=0.03 is invalid; expected a positive step that divides dt=0.1"):
        pendulum.with_hidden_effect([ViscousFriction(Constant(1.2))], step_size=0.03)


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Pendulum(dt=-0.1), "Pendulum: dt=-0.1 is invalid; expected a positive number"),
        (lambda: Pendulum(n_obs=0), "Pendulum: n_obs=0 is invalid; expected an integer >= 1"),
        (lambda: Pendulum(method="dopri5"), "Pendulum: method='dopri5' is invalid; expected one of torchdiffeq's fixed-step"),
        (lambda: Pendulum(omega=2.0), r"Pendulum: omega=2.0 is invalid; expected a Prior \(otgb.physics.Uniform"),
        (lambda: Pendulum(hidden_effect=[1.2]), r"Pendulum: hidden_effect\[0\]=1.2 is invalid; expected an otgb.physics.Term"),
        (lambda: ViscousFriction(1.2), "ViscousFriction: xi=1.2 is invalid; expected a Prior"),
        (lambda: Pendulum(hidden_effect=[ViscousFriction(Constant(1.0), velocity_index=2)]), "ViscousFriction: velocity_index=2"),
        (lambda: Uniform(1.0, 0.5), r"Uniform: \(low, high\)=\(1.0, 0.5\) is invalid; expected finite numbers with low < high"),
        (lambda: Choice([]), r"Choice: values=\[\] is invalid; expected a non-empty list of finite numbers"),
        (lambda: Constant(float("inf")), "Constant: value=inf is invalid; expected a finite number"),
    ],
)
def test_bad_constructor_arguments_raise_input_error_naming_class_argument_and_expectation(build, message):
    with pytest.raises(InputError, match=message):
        build()


def test_diverging_solve_raises(pendulum):
    x0, theta = torch.tensor([[0.5, 0.0], [0.1, 0.0]]), torch.tensor([[1.0], [float("nan")]])
    with pytest.raises(SimulationDiverged, match="1 of 2 trajectories.*index 1"):
        pendulum.simulate(x0, theta)
