"""The PhysicsModel / Term contract: declarations, recorded arguments (the cache key), priors, defaults."""

from collections.abc import Sequence
from pathlib import Path

import pytest
import torch
from jsonargparse import lazy_instance

from otgb.data import SimulationDataModule
from otgb.errors import InputError
from otgb.physics import (
    Advection,
    AdvectionDiffusion,
    Augmented,
    Choice,
    Constant,
    ConstantDrain,
    FieldModel,
    FitzHughNagumoReaction,
    LibraryTerm,
    Pendulum,
    PhysicsModel,
    Prior,
    ReactionDiffusion,
    Term,
    Uniform,
    ViscousFriction,
)


class Oscillator(PhysicsModel):
    """A harmonic oscillator x'' = -k x observed through its position (a newcomer's own system).

    Args:
        k: prior of the stiffness k.
        position: prior of the initial position.
        velocity: prior of the initial velocity.
        dt: time between two observations.
        n_obs: number of observations.
        hidden_effect: terms added to f_p.
    """

    state_names = ("position", "velocity")
    observed = ("position",)
    theta_names = ("k",)

    def __init__(
        self,
        k: Prior = lazy_instance(Uniform, low=1.0, high=4.0),
        position: Prior = lazy_instance(Uniform, low=-1.0, high=1.0),
        velocity: Prior = lazy_instance(Constant, value=0.0),
        dt: float = 0.1,
        n_obs: int = 40,
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        super().__init__(dt, n_obs, hidden_effect=hidden_effect)

    def field(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        x, v = state[:, 0], state[:, 1]
        return torch.stack([v, -theta[:, 0] * x], dim=1)


def test_a_new_ode_system_is_one_class_with_declared_names_and_priors(generator):
    model = Oscillator()
    assert (model.state_shape, model.obs_shape, model.trajectory_shape, model.theta_dim) == ((2,), (1,), (40, 1), 1)
    x0, theta = model.sample_initial_state(256, generator), model.sample_theta(256, generator)
    assert x0.shape == (256, 2) and (x0[:, 1] == 0).all() and (x0[:, 0].abs() <= 1).all()
    assert theta.shape == (256, 1) and (theta >= 1).all() and (theta <= 4).all()
    x = model.simulate(x0, theta)
    assert x.shape == (256, 40, 1) and torch.equal(x[:, 0, 0], x0[:, 0])
    dgp = model.with_hidden_effect([ViscousFriction(Constant(0.5))])
    y = dgp.simulate(x0, theta, dgp.sample_effect_params(256, generator))
    assert y[:, -10:].abs().amax() < x[:, -10:].abs().amax(), "friction damps the oscillation"
    assert repr(dgp) == (
        "Oscillator(k=Uniform(low=1.0, high=4.0), position=Uniform(low=-1.0, high=1.0), velocity=Constant(value=0.0), "
        "dt=0.1, n_obs=40, hidden_effect=(ViscousFriction(xi=Constant(value=0.5), position_index=0, velocity_index=1),))"
    )


def test_observe_selects_the_declared_components_along_the_component_axis():
    class Three(Oscillator):
        state_names = ("x", "y", "z")
        observed = ("x", "z")
        theta_names = ()

        def __init__(self) -> None:
            super().__init__()

        def sample_initial_state(self, n: int, generator: torch.Generator) -> torch.Tensor:
            return torch.rand(n, 3, generator=generator)

    states = torch.arange(4 * 5 * 3.0).reshape(4, 5, 3)
    assert Three().obs_shape == (2,)
    assert torch.equal(Three().observe(states), states[..., [0, 2]])
    assert torch.equal(Oscillator().observe(states[..., :2]), states[..., :1])
    fields = torch.randn(3, 7, 2, 8, 8)
    assert ReactionDiffusion(n_grid=8).observe(fields) is fields, "a field observes all its channels by default"
    assert ReactionDiffusion.observed == ("u", "v") and AdvectionDiffusion.state_names == ("T",)
    two_channels = type("TwoChannels", (AdvectionDiffusion,), {"state_names": ("T", "S")})
    assert two_channels.observed == ("T", "S"), "observed defaults to all states of the class that declares them"
    assert type("Longer", (Pendulum,), {"state_names": ("angle", "velocity", "x")}).observed == ("angle",)


def test_declarations_are_validated_when_the_class_is_made():
    with pytest.raises(TypeError, match=r"Twice.state_names repeats a name: \('x', 'x'\)"):
        type("Twice", (Oscillator,), {"state_names": ("x", "x"), "observed": ("x",)})
    with pytest.raises(TypeError, match=r"Hidden.observed names \['w'\], which are not in state_names"):
        type("Hidden", (Oscillator,), {"observed": ("w",)})
    with pytest.raises(TypeError, match="Backwards.observed .* must follow the order of state_names"):
        type("Backwards", (Oscillator,), {"observed": ("velocity", "position")})
    with pytest.raises(TypeError, match=r"Clash: \[.position.\] named twice among theta_names, state_names and input_names"):
        type("Clash", (Oscillator,), {"theta_names": ("position",)})
    with pytest.raises(TypeError, match="Loose.theta_names must be a tuple of names"):
        type("Loose", (Oscillator,), {"theta_names": "k"})
    with pytest.raises(TypeError, match=r"Stray.units names \['speed'\], which are neither 't' nor in state_names"):
        type("Stray", (Oscillator,), {"units": {"t": "s", "speed": "m/s"}})
    with pytest.raises(TypeError, match=r"Blank.units must map names \(str\) to units \(non-empty str\)"):
        type("Blank", (Oscillator,), {"units": {"t": ""}})


def test_axis_labels_carry_the_declared_units_also_for_the_augmented_physics():
    pendulum = Pendulum()
    drag = LibraryTerm("velocity*|velocity|", "velocity", Constant(-0.5))
    for model in (pendulum, Augmented(pendulum, [drag])):
        assert [model.axis_label(name) for name in ("t", "angle", "omega")] == ["t (s)", "angle (rad)", "omega (rad/s)"]
    assert AdvectionDiffusion().axis_label("t") == "t", "a model that declares no unit labels its axes bare"


def test_required_methods_are_abstract_and_default_samplers_need_priors():
    class NoField(PhysicsModel):
        state_names, theta_names = ("x",), ()

        def __init__(self, x: Prior = Constant(0.0)) -> None:
            super().__init__(0.1, 5)

    with pytest.raises(TypeError, match="abstract .*field"):
        NoField()

    class NoInitialField(FieldModel):
        state_names, theta_names = ("T",), ()

        def __init__(self) -> None:
            super().__init__((8,), 0.1, "periodic", 0.1, 5)

        def field(self, state, theta):
            return self.laplacian(state)

    with pytest.raises(TypeError, match="abstract .*sample_initial_state"):
        NoInitialField()

    class NoPrior(Oscillator):
        def __init__(self, position: Prior = Constant(0.0), velocity: Prior = Constant(0.0)) -> None:
            super().__init__(position=position, velocity=velocity)

    with pytest.raises(InputError, match="NoPrior draws 'k' from its prior, but its constructor has no argument 'k'"):
        NoPrior()


def test_repr_records_every_constructor_argument_so_cache_keys_differ(tmp_path):
    narrow, wide = Pendulum(omega=Uniform(1, 2)), Pendulum(omega=Uniform(5, 9))
    assert repr(narrow) != repr(wide)

    def key(physics: PhysicsModel, **kwargs) -> str:
        kwargs = {"hidden_effect": [ConstantDrain(Constant(0.0))], **kwargs}  # generated measurements need a DGP
        return SimulationDataModule(physics, cache_dir=str(tmp_path), **kwargs).source._key("measured", 10)

    assert key(narrow) != key(wide)
    assert repr(ConstantDrain(Constant(1.0), channel=0)) != repr(ConstantDrain(Constant(1.0), channel=1))
    term = [FitzHughNagumoReaction(Constant(5e-3))]
    model = ReactionDiffusion(n_grid=8)
    assert key(model, hidden_effect=term, measured_step_size=1e-3) != key(model, hidden_effect=term, measured_step_size=1e-2)
    assert key(model, hidden_effect=term) != key(model, hidden_effect=[FitzHughNagumoReaction(Constant(6e-3))])

    class Stiffer(Pendulum):
        def field(self, state, theta):
            return 2 * super().field(state, theta)

    assert repr(Stiffer()).startswith("Stiffer(") and key(Stiffer()) != key(Pendulum())


def test_defaults_print_like_the_explicit_arguments():
    explicit = Pendulum(omega=Uniform(0.785, 3.14), angle=Uniform(-1.57, 1.57), velocity=Constant(0.0))
    assert (
        repr(Pendulum())
        == repr(explicit)
        == (
            "Pendulum(omega=Uniform(low=0.785, high=3.14), angle=Uniform(low=-1.57, high=1.57), velocity=Constant(value=0.0), "
            "drive=None, dt=0.1, n_obs=50, step_size=None, method='rk4', hidden_effect=())"
        )
    )
    assert repr(Pendulum(hidden_effect=[ViscousFriction(Choice([0.6, 1.5]))])) == repr(
        Pendulum(hidden_effect=(ViscousFriction(Choice((0.6, 1.5))),))
    ), "lists and tuples print alike"


# Sums over draws and trajectories recorded with the code before priors became constructor arguments
# (commit 794fac0): the default simulators and their generator order are unchanged.
RECORDED = {
    "pendulum": (lambda: Pendulum(), 16, [-4.2227795124053955, 32.73293662071228, 0.0, 13.695934377843514]),
    "pendulum_2m": (
        lambda: Pendulum().with_hidden_effect([ViscousFriction(Choice([0.6, 1.5]))]),
        16,
        [-4.2227795124053955, 32.73293662071228, 19.50000011920929, -61.48756006824988],
    ),
    "advdiff_mm": (
        lambda: AdvectionDiffusion().with_hidden_effect([Advection(Uniform(0.01, 0.1))]),
        8,
        [99.27390590551795, 0.33579260390251875, 0.5128131881356239, 4780.676399604274],
    ),
    "reactdiff": (
        lambda: ReactionDiffusion(u_reaction=False),
        3,
        [3057.6478971242905, 0.01989922858774662, 0.0, 45766.11376700923],
    ),
    "reactdiff_k": (
        lambda: ReactionDiffusion(u_reaction=True).with_hidden_effect([ConstantDrain(Constant(5e-3))]),
        2,
        [2028.5808113217354, 0.013986454345285892, 0.009999999776482582, 24271.023312457604],
    ),
}


@pytest.mark.parametrize("name", list(RECORDED))
def test_default_simulators_draw_and_simulate_as_before(name):
    build, n, expected = RECORDED[name]
    model, generator = build(), torch.Generator().manual_seed(0)
    x0, theta = model.sample_initial_state(n, generator), model.sample_theta(n, generator)
    effect = model.sample_effect_params(n, generator)
    y = model.simulate(x0, theta, effect)
    sums = [float(t.double().sum()) for t in (x0, theta, effect, y)]
    assert sums == pytest.approx(expected, rel=1e-6, abs=1e-9)


def test_joint_prior_draws_follow_each_prior(generator):
    draws = Pendulum(omega=Choice([1.0, 2.0]), angle=Constant(0.3), velocity=Uniform(-1, 1)).sample_theta(2000, generator)
    assert set(draws.flatten().tolist()) == {1.0, 2.0} and 0.45 < (draws == 2.0).float().mean() < 0.55
    x0 = Pendulum(angle=Constant(0.3), velocity=Uniform(-1, 1)).sample_initial_state(2000, generator)
    assert (x0[:, 0] == 0.3).all() and -1 <= x0[:, 1].min() < -0.9 and 0.9 < x0[:, 1].max() <= 1


def test_a_prior_argument_goes_through_the_cli(tmp_path, capsys):
    from otgb.cli import main
    from otgb.command import OTGBCLI
    from otgb.training import MapTraining

    config = str(Path(__file__).parents[1] / "configs" / "pendulum.yaml")
    override = ["--data.physics.init_args.omega", "{class_path: otgb.physics.Uniform, init_args: {low: 1, high: 2}}"]
    with pytest.raises(SystemExit):
        main(["fit", "--config", config, *override, "--print_config"])
    printed = capsys.readouterr().out
    assert (
        "omega:\n        class_path: otgb.physics.Uniform\n        init_args:\n          low: 1.0\n          high: 2.0" in printed
    )
    assert "velocity:\n        class_path: otgb.physics.Constant\n        init_args:\n          value: 0.0" in printed
    args = ["--config", config, *override, f"--data.cache_dir={tmp_path}", "--trainer.logger=false"]
    physics = OTGBCLI(MapTraining, SimulationDataModule, run=False, args=args).datamodule.physics
    assert repr(physics) == repr(Pendulum(omega=Uniform(1.0, 2.0)))
