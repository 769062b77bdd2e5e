"""Two maps with nothing to learn, for the rows every table needs beside the learned maps.

Scored by ``otgb test`` like any map (the same evaluation code path, no checkpoint):

- :class:`IdentityMap`, "f_p only": y = x, how far the incomplete physics is on its own;
- :class:`CompletePhysicsMap`, "complete physics": the data-generating process's own simulator
  (f_p plus the true hidden terms) at the training solver's step, the floor that the solver and
  the sampling set, above the Reference (measured half against measured half).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from otgb.physics.base import PhysicsModel, Term


class IdentityMap(nn.Module):
    """y = x: the source simulation of f_p itself."""

    def __init__(self, physics: PhysicsModel, z_dim: int) -> None:
        super().__init__()

    def forward(self, x: Tensor, initial_state: Tensor, theta: Tensor, z: Tensor, signals: Tensor | None = None) -> Tensor:
        return x


class CompletePhysicsMap(nn.Module):
    """f_p plus the true hidden terms, solved from the input's (x0, theta) with f_p's own solver and step.

    A random hidden parameter (one-to-many) is drawn per trajectory from its prior by the map's
    own generator, seeded by ``seed``: the same run gives the same draws.

    Args:
        physics: f_p, whose inputs and observation the map takes and gives.
        z_dim: dimension of the latent z (not used: the terms' priors are the randomness).
        hidden_effect: the terms the data-generating process adds to f_p (``data.hidden_effect``).
        seed: seed of the hidden parameters' draws.
    """

    def __init__(self, physics: PhysicsModel, z_dim: int, hidden_effect: Sequence[Term], seed: int = 0) -> None:
        super().__init__()
        self.dgp = physics.with_hidden_effect(hidden_effect)
        self.seed = seed
        self._generator: torch.Generator | None = None

    def forward(self, x: Tensor, initial_state: Tensor, theta: Tensor, z: Tensor, signals: Tensor | None = None) -> Tensor:
        if self._generator is None:
            self._generator = torch.Generator().manual_seed(self.seed)
        effect = self.dgp.sample_effect_params(len(theta), self._generator).to(theta)
        return self.dgp.simulate(initial_state, theta, effect, signals)
