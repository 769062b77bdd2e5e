"""Named physical terms: the building blocks of a DGP's hidden effect."""

from __future__ import annotations

import torch
from torch import Tensor

from otgb.physics.base import Term
from otgb.physics.priors import Prior


class ViscousFriction(Term):
    """Viscous friction -xi * velocity on the rate of change of the velocity component.

    Args:
        xi: prior of the friction coefficient, drawn once per trajectory.
        position_index / velocity_index: where position and velocity sit in the state vector.
    """

    def __init__(self, xi: Prior, position_index: int = 0, velocity_index: int = 1) -> None:
        super().__init__({"xi": xi})
        self.position_index, self.velocity_index = position_index, velocity_index

    def forward(self, state: Tensor, params: Tensor) -> Tensor:
        out = torch.zeros_like(state)
        out[:, self.velocity_index] = -params[:, 0] * state[:, self.velocity_index]
        return out
