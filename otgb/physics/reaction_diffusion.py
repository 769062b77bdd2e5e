"""Reaction-diffusion, FitzHugh-Nagumo (paper, Reaction-Diffusion) on a periodic 2-D grid.

The full process is

    du/dt = a Lap(u) + u - u^3 - v - k,      dv/dt = b Lap(v) + u - v

on an n x n grid over [-1, 1]^2 (dx = 2 / n), periodic boundaries, u(0), v(0) ~ U(0, 1) per
cell; theta = (a, b). f_p is this model without the terms the DGP adds:

- ``u_reaction=False`` (the official code's f_p, behind the paper's Table 1):
  f_p = [a Lap(u), b Lap(v) + u - v]; the DGP adds :class:`FitzHughNagumoReaction`.
- ``u_reaction=True`` (the paper's text): f_p = [a Lap(u) + u - u^3 - v, b Lap(v) + u - v];
  the DGP adds only the threshold, :class:`ConstantDrain` (-k on u).

The state and the observation are (2, n, n); the trajectory is the ``n_obs`` frames after
the initial state, at t = dt, 2 dt, ..., shape (n_obs, 2, n, n).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from otgb.physics.arguments import invalid
from otgb.physics.base import FieldModel, Term
from otgb.physics.priors import Prior, Uniform, default_prior


class ReactionDiffusion(FieldModel):
    """FitzHugh-Nagumo's known part on a periodic square grid, 15 frames at dt = 0.1 by default.

    Args:
        a: prior of the diffusion coefficient a of u, drawn once per trajectory.
        b: prior of the diffusion coefficient b of v, drawn once per trajectory.
        u_reaction: whether f_p knows the u-reaction u - u^3 - v (see the module docstring).
        n_grid: grid points per side of [-1, 1]^2, at least 3; dx = 2 / n_grid.
        dt: time between two frames.
        n_obs: number of frames, the first at t = dt.
        step_size: solver step, a divisor of dt; defaults to dt.
        method: a torchdiffeq fixed-step method ("rk4", "euler", "midpoint", ...).
        hidden_effect: terms added to f_p; empty for f_p (the data module adds the DGP's).
    """

    state_names = ("u", "v")
    theta_names = ("a", "b")

    def __init__(
        self,
        a: Prior = default_prior(Uniform, low=1e-3, high=2e-3),
        b: Prior = default_prior(Uniform, low=3e-3, high=7e-3),
        u_reaction: bool = False,
        n_grid: int = 32,
        dt: float = 0.1,
        n_obs: int = 15,
        step_size: float | None = None,
        method: str = "rk4",
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        if not (isinstance(n_grid, int) and n_grid >= 3):
            raise invalid(self, "n_grid", n_grid, "an integer >= 3")
        if not isinstance(u_reaction, bool):
            raise invalid(self, "u_reaction", u_reaction, "true or false")
        super().__init__((n_grid, n_grid), 2.0 / n_grid, "periodic", dt, n_obs, False, step_size, method, hidden_effect)
        self.n_grid, self.u_reaction = n_grid, u_reaction

    def field(self, state: Tensor, theta: Tensor) -> Tensor:
        diffusion = theta.reshape(-1, 2, 1, 1) * self.laplacian(state)
        u, v = state[:, 0], state[:, 1]
        du = diffusion[:, 0] + (u - u**3 - v if self.u_reaction else 0.0)
        dv = diffusion[:, 1] + u - v
        return torch.stack([du, dv], dim=1)

    def coordinates(self, device: torch.device | None = None, dtype: torch.dtype = torch.float32) -> tuple[Tensor, ...]:
        """x and y of every cell of the square [-1, 1)^2: -1, -1 + dx, ..., 1 - dx along each axis."""
        return tuple(position - 1.0 for position in super().coordinates(device, dtype))

    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        """u(0), v(0) ~ U(0, 1) independently in every cell."""
        return torch.rand(n, *self.state_shape, generator=generator)
