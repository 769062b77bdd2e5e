"""Advection-diffusion (paper, Advection-Diffusion): f_p is the heat equation on a 1-D grid.

    dT/dt = alpha d^2T/ds^2            (f_p; the DGP adds -beta dT/ds, :class:`Advection`)

on ``n_grid`` points s_i = i dx (i = 1..n_grid) with zero Dirichlet values at s = 0 and
s = (n_grid + 1) dx, second-order central differences, RK4. The initial profile is
T(0, s) = c sin(pi s / 2) with c drawn per trajectory; theta = (alpha,). The state and the
observation are the whole field, shape (1, n_grid): one channel over space.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from otgb.physics.base import PhysicsModel, Term, check_range, uniform_box
from otgb.physics.stencils import laplacian


class AdvectionDiffusion(PhysicsModel):
    """1-D diffusion observed at all grid points, 50 frames at dt = 0.02 by default.

    Args:
        alpha_range: prior U(low, high) of the diffusion coefficient alpha.
        amplitude_range: prior U(low, high) of the initial amplitude c.
        n_grid, dx: grid points and spacing.
    """

    theta_names = ("alpha",)
    boundary = "dirichlet"

    def __init__(
        self,
        alpha_range: tuple[float, float] = (0.01, 0.1),
        amplitude_range: tuple[float, float] = (0.5, 1.5),
        n_grid: int = 20,
        dx: float = 0.1,
        dt: float = 0.02,
        n_obs: int = 50,
        step_size: float | None = None,
        method: str = "rk4",
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        super().__init__(dt, n_obs, True, step_size, method, hidden_effect)
        if n_grid < 3 or not dx > 0:
            raise ValueError(f"AdvectionDiffusion: need n_grid >= 3 and dx > 0, got n_grid={n_grid}, dx={dx}")
        self.alpha_range = check_range("AdvectionDiffusion.alpha_range", alpha_range)
        self.amplitude_range = check_range("AdvectionDiffusion.amplitude_range", amplitude_range)
        self.n_grid, self.dx = int(n_grid), float(dx)
        self.state_shape = self.obs_shape = (1, self.n_grid)

    @property
    def grid(self) -> Tensor:
        """Positions s_i of the grid points, (n_grid,)."""
        return torch.arange(1, self.n_grid + 1, dtype=torch.float32) * self.dx

    def field(self, state: Tensor, theta: Tensor) -> Tensor:
        alpha = theta[:, :1, None]
        return alpha * laplacian(state, self.dx, self.boundary, dims=1)

    def observe(self, state: Tensor) -> Tensor:
        return state

    def sample_theta(self, n: int, generator: torch.Generator) -> Tensor:
        return uniform_box([self.alpha_range[0]], [self.alpha_range[1]], n, generator)

    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        amplitude = uniform_box([self.amplitude_range[0]], [self.amplitude_range[1]], n, generator)
        profile = torch.sin(math.pi * self.grid / 2)
        return (amplitude * profile).unsqueeze(1)

    def extra_repr(self) -> str:
        return (
            f"alpha_range={self.alpha_range}, amplitude_range={self.amplitude_range}, n_grid={self.n_grid}, "
            f"dx={self.dx}, dt={self.dt}, n_obs={self.n_obs}, step_size={self.step_size}, method={self.method!r}"
        )
