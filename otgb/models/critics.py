"""Critics (potentials f_psi) on whole observed trajectories."""

from __future__ import annotations

import math
from collections.abc import Sequence

from torch import Tensor, nn

from otgb.models.layers import activation


class MLPCritic(nn.Module):
    """MLP on the flattened trajectory (paper, App. E: hidden [250, 100, 100, 50]).

    Args:
        trajectory_shape: (T, *obs_shape) of one trajectory.
    """

    def __init__(
        self, trajectory_shape: Sequence[int], hidden: Sequence[int] = (250, 100, 100, 50), activation_name: str = "ELU"
    ) -> None:
        super().__init__()
        widths = [math.prod(trajectory_shape), *hidden]
        layers: list[nn.Module] = []
        for w, w_next in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(w, w_next), activation(activation_name)]
        self.net = nn.Sequential(*layers, nn.Linear(widths[-1], 1))

    def forward(self, y: Tensor) -> Tensor:
        """y (N, T, *obs) -> (N,)."""
        return self.net(y.flatten(1)).squeeze(1)
