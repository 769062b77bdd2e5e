"""Named physical terms: the building blocks of a DGP's hidden effect."""

from __future__ import annotations

import torch
from torch import Tensor

from otgb.errors import InputError
from otgb.physics.base import FieldModel, PhysicsModel, Term
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

    def forward(self, state: Tensor, params: Tensor, model: PhysicsModel) -> Tensor:
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

    def forward(self, state: Tensor, params: Tensor, model: FieldModel) -> Tensor:
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

    def forward(self, state: Tensor, params: Tensor, model: PhysicsModel) -> Tensor:
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

    def forward(self, state: Tensor, params: Tensor, model: PhysicsModel) -> Tensor:
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
