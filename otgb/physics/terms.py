"""Named physical terms: the building blocks of a DGP's hidden effect."""

from __future__ import annotations

import re

import torch
from torch import Tensor

from otgb.errors import InputError
from otgb.physics.base import FieldModel, PhysicsModel, Term
from otgb.physics.features import evaluate_feature, parse_feature, variable_values
from otgb.physics.forms import form_named
from otgb.physics.priors import Prior


class ViscousFriction(Term):
    """Viscous friction -xi * velocity on the rate of change of the velocity component.

    Args:
        xi: prior of the friction coefficient, drawn once per trajectory.
        position_index: where the position sits in the state vector.
        velocity_index: where the velocity sits in the state vector; the friction acts on it.
    """

    def __init__(self, xi: Prior, position_index: int = 0, velocity_index: int = 1) -> None:
        super().__init__({"xi": xi})
        self.position_index, self.velocity_index = position_index, velocity_index

    def check_model(self, model: PhysicsModel) -> None:
        super().check_model(model)
        _check_index(self, "velocity_index", self.velocity_index, model)

    def forward(self, state: Tensor, params: Tensor, model: PhysicsModel, theta: Tensor | None = None) -> Tensor:
        out = torch.zeros_like(state)
        out[:, self.velocity_index] = -params[:, 0] * state[:, self.velocity_index]
        return out


def _column(params: Tensor, state: Tensor) -> Tensor:
    """The first parameter as (B, 1, ..., 1), broadcastable against ``state``."""
    return params[:, 0].reshape(-1, *([1] * (state.dim() - 1)))


class Advection(Term):
    """Advection -beta dT/ds along the last axis, by central differences on the model's grid.

    Args:
        beta: prior of the advection speed, drawn once per trajectory.
    """

    model_type = FieldModel

    def __init__(self, beta: Prior) -> None:
        super().__init__({"beta": beta})

    def forward(self, state: Tensor, params: Tensor, model: FieldModel, theta: Tensor | None = None) -> Tensor:
        return -_column(params, state) * model.derivative(state)


class FitzHughNagumoReaction(Term):
    """The u-reaction of FitzHugh-Nagumo, u - u^3 - v - k, on channel 0 of a (u, v) state.

    Args:
        k: prior of the threshold k, drawn once per trajectory.
    """

    def __init__(self, k: Prior) -> None:
        super().__init__({"k": k})

    def check_model(self, model: PhysicsModel) -> None:
        super().check_model(model)
        if model.state_shape[0] != 2:
            raise InputError(
                f"FitzHughNagumoReaction acts on a (u, v) state; {type(model).__name__} has the components {model.state_names}"
            )

    def forward(self, state: Tensor, params: Tensor, model: PhysicsModel, theta: Tensor | None = None) -> Tensor:
        u, v = state[:, 0], state[:, 1]
        reaction = u - u**3 - v - _column(params, u)
        return torch.stack([reaction, torch.zeros_like(v)], dim=1)


class ConstantDrain(Term):
    """A constant sink -k on one channel of the state (FitzHugh-Nagumo's threshold k alone).

    Args:
        k: prior of the drain rate, drawn once per trajectory.
        channel: index of the state component (channel) it acts on.
    """

    def __init__(self, k: Prior, channel: int = 0) -> None:
        super().__init__({"k": k})
        self.channel = channel

    def check_model(self, model: PhysicsModel) -> None:
        super().check_model(model)
        _check_index(self, "channel", self.channel, model)

    def forward(self, state: Tensor, params: Tensor, model: PhysicsModel, theta: Tensor | None = None) -> Tensor:
        out = torch.zeros_like(state)
        out[:, self.channel] = -_column(params, state[:, self.channel])
        return out


def _check_index(term: Term, name: str, index: int, model: PhysicsModel) -> None:
    """``index`` must pick one of the model's state components."""
    size = len(model.state_names)
    if not (isinstance(index, int) and 0 <= index < size):
        raise InputError(
            f"{type(term).__name__}: {name}={index!r} is invalid; expected an index 0..{size - 1} "
            f"into the state components {model.state_names} of {type(model).__name__}"
        )


class LibraryTerm(Term):
    """``coefficient * feature`` added to d(component)/dt: any named effect, one class.

    The feature is written in the model's variable names (grammar: :mod:`otgb.physics.features`),
    e.g. ``velocity`` on ``velocity`` with coefficient -1.2 is viscous friction, ``velocity*|velocity|``
    quadratic drag, ``d_s(T)`` on ``T`` advection, ``u^3`` on ``u`` a cubic reaction. It serves as a
    hidden effect of a synthetic DGP and as a named term of an augmented physics model
    (:class:`otgb.physics.Augmented`), where the coefficient becomes a physics parameter.

    Args:
        feature: the feature, e.g. ``velocity*|velocity|`` or ``lap(u)``.
        component: the state component whose rate of change the term adds to.
        coefficient: prior of the coefficient, drawn once per trajectory.
        name: the coefficient's parameter name (default from component and feature, e.g.
            ``c_velocity__velocity_x_abs_velocity`` for ``velocity*|velocity|`` on ``velocity``).
    """

    def __init__(self, feature: str, component: str, coefficient: Prior, name: str | None = None) -> None:
        super().__init__({"coefficient": coefficient})
        self.feature, self.component = feature, component
        self.name = name if name is not None else coefficient_name(feature, component)
        self._factors = None

    @property
    def parameter_names(self) -> list[str]:
        """Its column of an augmented model's theta: the coefficient."""
        return [self.name]

    def check_model(self, model: PhysicsModel) -> None:
        super().check_model(model)
        if self.component not in model.state_names:
            raise InputError(
                f"LibraryTerm: component={self.component!r} is invalid; expected one of {type(model).__name__}'s "
                f"state names {model.state_names}"
            )
        self._factors = parse_feature(self.feature, model)

    takes_inputs = True

    def forward(
        self, state: Tensor, params: Tensor, model: PhysicsModel, theta: Tensor | None = None, inputs: Tensor | None = None
    ) -> Tensor:
        value = self.rate(state, params, model, theta, inputs=inputs)
        index = model.state_names.index(self.component)
        parts = [value if i == index else torch.zeros_like(value) for i in range(state.shape[1])]
        return torch.stack(parts, dim=1)

    def rate(
        self, state: Tensor, params: Tensor, model: PhysicsModel, theta: Tensor | None, powers: dict | None = None,
        inputs: Tensor | None = None,
    ) -> Tensor:  # fmt: skip
        """What the term adds to d(component)/dt: (B, *grid); ``powers`` and ``inputs`` as in
        :func:`otgb.physics.features.evaluate_feature`."""
        if self._factors is None:
            self.check_model(model)
        return _column(params, state[:, 0]) * evaluate_feature(self._factors, state, theta, model, powers, inputs)


def coefficient_name(feature: str, component: str) -> str:
    """A parameter name (a Python identifier) for the coefficient of ``feature`` on ``component``."""
    text = re.sub(r"\|(\w+)\|", r"abs_\1", feature.replace("*", "_x_").replace("^", "_pow"))
    return re.sub(r"\W+", "_", f"c_{component}__{text}").strip("_")


class FormTerm(Term):
    """``coefficient * shape(variables; parameters)`` added to d(component)/dt, every parameter drawn from a prior
    once per trajectory (a hidden effect of a DGP, or the model a fit moves the parameters of).

    Args:
        form: a built-in form (``saturating``, ``rational``, ``stribeck``, ``power``, ``exponential``, ``bump``,
            ``bump2``) or the class path of an :class:`otgb.physics.forms.Form`.
        component: the state component whose rate of change the term adds to.
        variables: the state components or grid coordinates the shape is a function of.
        coefficient: prior of the coefficient c.
        parameters: prior of each of the form's parameters, by name.
    """

    def __init__(self, form: str, component: str, variables: list[str], coefficient: Prior, parameters: dict[str, Prior]) -> None:
        shape = form_named(form)
        variables = [variables] if isinstance(variables, str) else list(variables)
        names = tuple(shape.parameters)
        if len(variables) != shape.arity or tuple(parameters) != names:
            raise InputError(
                f"FormTerm: the form {form!r} takes {shape.arity} variable(s) and the parameters {list(names)}; "
                f"got variables={variables} and parameters={list(parameters)}"
            )
        super().__init__({"coefficient": coefficient, **parameters})
        self.form, self.form_name, self.component, self.variables = shape, form, component, variables
        self.name = f"c_{component}__{form.rpartition('.')[2]}_{'_'.join(variables)}"

    @property
    def parameter_names(self) -> list[str]:
        """Its columns of an augmented model's theta: the coefficient, then each parameter."""
        return [self.name, *(f"{self.name}__{p}" for p in self.form.parameters)]

    def check_model(self, model: PhysicsModel) -> None:
        super().check_model(model)
        known = (*model.state_names, *model.input_names, *getattr(model, "coordinate_names", ()))
        wrong = [n for n in self.variables if n not in known]
        wrong += [] if self.component in model.state_names else [self.component]
        if wrong:
            raise InputError(
                f"FormTerm: {wrong} are not names of {type(model).__name__}; expected the component among "
                f"{model.state_names} and the variables among {known}"
            )

    takes_inputs = True

    def forward(
        self, state: Tensor, params: Tensor, model: PhysicsModel, theta: Tensor | None = None, inputs: Tensor | None = None
    ) -> Tensor:
        value = self.rate(state, params, model, theta, inputs=inputs)
        index = model.state_names.index(self.component)
        return torch.stack([value if i == index else torch.zeros_like(value) for i in range(state.shape[1])], dim=1)

    def rate(
        self, state: Tensor, params: Tensor, model: PhysicsModel, theta: Tensor | None, powers: dict | None = None,
        inputs: Tensor | None = None,
    ) -> Tensor:  # fmt: skip
        """What the term adds to d(component)/dt: (B, *grid), of the inputs' values ``inputs`` where it reads them."""
        columns = [params[:, k].reshape(-1, *([1] * (state.dim() - 2))) for k in range(params.shape[1])]
        variables = [variable_values(name, state, theta, model, inputs) for name in self.variables]
        return columns[0] * self.form.shape(variables, columns[1:])
