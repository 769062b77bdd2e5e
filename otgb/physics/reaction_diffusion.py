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

from otgb.physics.base import PhysicsModel, Term, check_range, uniform_box
from otgb.physics.stencils import laplacian


class ReactionDiffusion(PhysicsModel):
    """FitzHugh-Nagumo's known part on a periodic square grid, 15 frames at dt = 0.1 by default.

    Args:
        a_range, b_range: priors U(low, high) of the diffusion coefficients of u and v.
        u_reaction: whether f_p knows the u-reaction u - u^3 - v (see the module docstring).
        n_grid: grid points per side of [-1, 1]^2.
    """

    theta_names = ("a", "b")
    boundary = "periodic"

    def __init__(
        self,
        a_range: tuple[float, float] = (1e-3, 2e-3),
        b_range: tuple[float, float] = (3e-3, 7e-3),
        u_reaction: bool = False,
        n_grid: int = 32,
        dt: float = 0.1,
        n_obs: int = 15,
        step_size: float | None = None,
        method: str = "rk4",
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        super().__init__(dt, n_obs, False, step_size, method, hidden_effect)
        if n_grid < 3:
            raise ValueError(f"ReactionDiffusion: need n_grid >= 3, got {n_grid}")
        self.a_range = check_range("ReactionDiffusion.a_range", a_range)
        self.b_range = check_range("ReactionDiffusion.b_range", b_range)
        self.u_reaction = bool(u_reaction)
        self.n_grid, self.dx = int(n_grid), 2.0 / n_grid
        self.state_shape = self.obs_shape = (2, self.n_grid, self.n_grid)

    def field(self, state: Tensor, theta: Tensor) -> Tensor:
        diffusion = theta.reshape(-1, 2, 1, 1) * laplacian(state, self.dx, self.boundary, dims=2)
        u, v = state[:, 0], state[:, 1]
        du = diffusion[:, 0] + (u - u**3 - v if self.u_reaction else 0.0)
        dv = diffusion[:, 1] + u - v
        return torch.stack([du, dv], dim=1)

    def observe(self, state: Tensor) -> Tensor:
        return state

    def sample_theta(self, n: int, generator: torch.Generator) -> Tensor:
        return uniform_box([self.a_range[0], self.b_range[0]], [self.a_range[1], self.b_range[1]], n, generator)

    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        return torch.rand(n, *self.state_shape, generator=generator)

    def extra_repr(self) -> str:
        return (
            f"a_range={self.a_range}, b_range={self.b_range}, u_reaction={self.u_reaction}, n_grid={self.n_grid}, "
            f"dt={self.dt}, n_obs={self.n_obs}, step_size={self.step_size}, method={self.method!r}"
        )
