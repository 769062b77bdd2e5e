"""Gradients of a distribution-matching loss taken a chunk of simulated trajectories at a time: the same numbers as
in one graph, for the fit of coefficients and for their intervals, with the graph's memory bounded."""

import pytest
import torch

import otgb.discovery.chunked as chunked
from otgb.data import generate_measured
from otgb.discovery.chunked import backward_in_chunks, chunk_size, saved_bytes
from otgb.discovery.discrepancy import Target, discrepancy_and_rows
from otgb.discovery.intervals import sandwich_intervals
from otgb.discovery.library import build_library
from otgb.discovery.refine import fit
from otgb.physics import Pendulum, ReactionDiffusion, ViscousFriction
from otgb.physics.augmented import Augmented
from otgb.physics.priors import Constant
from otgb.physics.terms import LibraryTerm


def _field_simulator(n: int, coefficients: torch.Tensor):
    """A 6x6 reaction-diffusion field with two library terms whose coefficients (n, 2) are ``coefficients``."""
    field = ReactionDiffusion(n_grid=6, n_obs=4)
    model = Augmented(field, [LibraryTerm("u*v", "u", Constant(0.0)), LibraryTerm("lap(v)", "v", Constant(0.0))])
    g = torch.Generator().manual_seed(0)
    x0, theta = field.sample_initial_state(n, g), field.sample_theta(n, g)

    def simulate(rows: slice) -> torch.Tensor:
        return model.observe(model.solve(model.vector_field, x0[rows], torch.cat([theta[rows], coefficients[rows]], 1)))

    return field, simulate


def _loss_and_gradient(budget, n=7, noise=0.0):
    coefficients = torch.tensor([[0.3, 0.002]]).repeat(n, 1).requires_grad_()
    field, simulate = _field_simulator(n, coefficients)
    target = Target.of(generate_measured(field, 9, 1)["y"].float())
    size = chunk_size(simulate, n, budget)
    with field.measured_with_noise(noise, seed=3):
        loss, simulated = backward_in_chunks(simulate, n, lambda s: discrepancy_and_rows(s, target)[0], size)
    return loss, simulated, coefficients.grad


def test_the_gradient_in_chunks_is_the_gradient_in_one_graph():
    """Chunks of one, two and three trajectories against one graph of all seven: the same loss, trajectories and
    gradient (to float rounding), and the gradient is not zero."""
    loss, simulated, gradient = _loss_and_gradient(budget=None)
    assert gradient.abs().sum() > 0
    _, simulate = _field_simulator(1, torch.zeros(1, 2))
    one = saved_bytes(lambda: simulate(slice(0, 1)))
    for budget in (1, 2 * one, 3 * one):
        chunked_loss, chunked_simulated, chunked_gradient = _loss_and_gradient(budget)
        assert torch.equal(chunked_loss, loss) and torch.equal(chunked_simulated, simulated)
        torch.testing.assert_close(chunked_gradient, gradient, rtol=1e-5, atol=1e-7)


def test_measurement_noise_leaves_the_chunked_gradient_exact():
    """With measurement noise in force each chunk draws its own noise, but it is added to the observations: the
    gradient is still the whole batch's, and the noise changed the loss."""
    loss, _, gradient = _loss_and_gradient(budget=None, noise=0.05)
    chunked_loss, _, chunked_gradient = _loss_and_gradient(budget=1, noise=0.05)
    assert torch.equal(chunked_loss, loss) and loss != _loss_and_gradient(budget=None)[0]
    torch.testing.assert_close(chunked_gradient, gradient, rtol=1e-5, atol=1e-7)


def test_a_loss_summed_over_groups_gives_the_same_gradient_a_group_at_a_time():
    """An interval's loss is a sum over its perturbed models, each a function of its own trajectories: taken a group at
    a time (the distances of one group's trajectories in memory at once), the loss and the gradient are the one
    graph's."""
    target = Target.of(generate_measured(ReactionDiffusion(n_grid=6, n_obs=4), 9, 1)["y"].float())

    def grouped(groups: int, budget: int | None) -> tuple[torch.Tensor, torch.Tensor]:
        coefficients = torch.tensor([[0.3, 0.002]] * 4 + [[0.2, 0.004]] * 4).requires_grad_()
        _, simulate = _field_simulator(8, coefficients)

        def loss_of(simulated: torch.Tensor) -> torch.Tensor:
            return sum(discrepancy_and_rows(group, target)[0] for group in simulated.unflatten(0, (-1, 4)))

        loss, _ = backward_in_chunks(simulate, 8, loss_of, chunk_size(simulate, 8, budget), groups=groups)
        return loss, coefficients.grad

    loss, gradient = grouped(1, None)
    assert gradient[:4].abs().sum() > 0 and gradient[4:].abs().sum() > 0
    for groups, budget in [(2, None), (2, 1)]:
        group_loss, group_gradient = grouped(groups, budget)
        torch.testing.assert_close(group_loss, loss, rtol=1e-6, atol=1e-8)
        torch.testing.assert_close(group_gradient, gradient, rtol=1e-5, atol=1e-7)


def test_the_chunk_holds_as_many_trajectories_as_the_budget_allows():
    _, simulate = _field_simulator(20, torch.zeros(20, 2, requires_grad=True))
    one = saved_bytes(lambda: simulate(slice(0, 1)))
    assert one > 6 * 6 * 2 * 4 * 4  # at least a state per observed frame was kept
    assert chunk_size(simulate, 20, 3 * one) == 3
    assert chunk_size(simulate, 20, one // 2) == 1
    assert chunk_size(simulate, 20, 100 * one) == 20


def test_a_diverging_simulation_gives_its_loss_without_a_gradient():
    coefficients = torch.ones(4, 1, requires_grad=True)

    def simulate(rows: slice) -> torch.Tensor:
        return torch.exp(1e4 * coefficients[rows])[:, None, :]

    loss, simulated = backward_in_chunks(simulate, 4, lambda s: (s - 1).abs().mean(), size=1)
    assert not torch.isfinite(loss) and coefficients.grad is None and simulated.shape == (4, 1, 1)


@pytest.fixture
def friction_fit():
    pendulum = Pendulum()
    measured = generate_measured(pendulum.with_hidden_effect([ViscousFriction(Constant(1.2))]), 200, 3)["y"]
    candidate = next(c for c in build_library(pendulum, ["velocity"]) if c.feature == "velocity")
    return pendulum, candidate, measured


def test_fit_and_intervals_are_the_same_with_a_graph_of_a_few_trajectories(friction_fit, monkeypatch):
    """A friction fit's first L-BFGS iteration, and the sandwich interval of a fit, with the graph of 128 trajectories
    at once and with chunks of 40. (Over many iterations the two drift apart as any two float roundings do: L-BFGS's
    line search amplifies differences of 1e-7.)"""
    pendulum, candidate, measured = friction_fit
    first_step = lambda: fit(pendulum, [candidate], [-0.6], "uniform", measured, measured, 1, 128, 0, False, [1.2])  # noqa: E731
    fitted = fit(pendulum, [candidate], [-0.6], "uniform", measured, measured, 10, 128, 0, False, [1.2])
    whole_step, whole_interval = first_step(), sandwich_intervals(pendulum, fitted, measured, 128, 0)
    model = Augmented(pendulum, [LibraryTerm("velocity", "velocity", Constant(0.0))])
    theta = torch.cat([pendulum.sample_theta(1, torch.Generator()), torch.zeros(1, 1, requires_grad=True)], 1)
    one = saved_bytes(lambda: model.solve(model.vector_field, torch.zeros(1, 2), theta))
    monkeypatch.setattr(chunked, "GRAPH_BYTES", 40 * one)
    chunked_step, chunked_interval = first_step(), sandwich_intervals(pendulum, fitted, measured, 128, 0)
    assert whole_step.priors[0].high < -1.5  # the first step moved far from -0.6
    for a, b in [
        (whole_step.priors[0].low, chunked_step.priors[0].low),
        (whole_step.priors[0].high, chunked_step.priors[0].high),
    ]:
        assert a == pytest.approx(b, rel=1e-5)
    assert whole_interval.centre[0][0] < -1.2 < whole_interval.centre[0][1]
    torch.testing.assert_close(torch.tensor(chunked_interval.centre), torch.tensor(whole_interval.centre), rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(torch.tensor(chunked_interval.width), torch.tensor(whole_interval.width), rtol=1e-4, atol=1e-6)
