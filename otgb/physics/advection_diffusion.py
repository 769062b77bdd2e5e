"""Advection-diffusion (paper, Advection-Diffusion): f_p is the heat equation on a 1-D grid.

    dT/dt = alpha d^2T/ds^2 + P(t)     (f_p; the DGP adds -beta dT/ds, :class:`Advection`)

on ``n_grid`` points s_i = i dx (i = 1..n_grid) with zero Dirichlet values at s = 0 and
s = (n_grid + 1) dx, second-order central differences, RK4. The initial profile is
T(0, s) = c sin(pi s / 2) with c drawn per trajectory; theta = (alpha,). The state and the
observation are the whole field, shape (1, n_grid): one channel over space. P(t) is a recorded
input, the power of a heater that warms the whole rod alike (per unit heat capacity): zero unless
a file records it (``u``, named ``power``) or a process draws it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from otgb.physics.arguments import invalid
from otgb.physics.base import FieldModel, Term
from otgb.physics.priors import Prior, Uniform, check_prior, default_prior, sample_joint
from otgb.physics.signals import InputProcess


class AdvectionDiffusion(FieldModel):
    """1-D diffusion observed at all grid points, 50 frames at dt = 0.02 by default.

    Args:
        alpha: prior of the diffusion coefficient alpha, drawn once per trajectory.
        amplitude: prior of the amplitude c of the initial profile c sin(pi s / 2).
        power: the process a generated DGP draws the heater's power P(t) from (e.g. ``otgb.physics.SumOfSines``);
            None: no heater, unless the measured file records its ``power``.
        n_grid: number of grid points, at least 3.
        dx: grid spacing; the zero Dirichlet ends lie at s = 0 and s = (n_grid + 1) dx.
        dt: time between two frames.
        n_obs: number of frames, the first at t = 0.
        step_size: solver step, a divisor of dt; defaults to dt.
        method: a torchdiffeq fixed-step method ("rk4", "euler", "midpoint", ...).
        hidden_effect: terms added to f_p; empty for f_p (the data module adds the DGP's).
    """

    state_names = ("T",)
    theta_names = ("alpha",)
    input_names = ("power",)

    def __init__(
        self,
        alpha: Prior = default_prior(Uniform, low=0.01, high=0.1),
        amplitude: Prior = default_prior(Uniform, low=0.5, high=1.5),
        power: InputProcess | None = None,
        n_grid: int = 20,
        dx: float = 0.1,
        dt: float = 0.02,
        n_obs: int = 50,
        step_size: float | None = None,
        method: str = "rk4",
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        if not (isinstance(n_grid, int) and n_grid >= 3):
            raise invalid(self, "n_grid", n_grid, "an integer >= 3")
        super().__init__((n_grid,), dx, "dirichlet", dt, n_obs, True, step_size, method, hidden_effect)
        self.n_grid = n_grid
        self.amplitude = check_prior(self, "amplitude", amplitude)

    @property
    def grid(self) -> Tensor:
        """Positions s_i of the grid points, (n_grid,)."""
        return self.coordinates()[0]

    def field(self, state: Tensor, theta: Tensor, inputs: Tensor | None = None) -> Tensor:
        alpha = theta[:, :1, None]
        diffusion = alpha * self.laplacian(state)
        return diffusion if inputs is None else diffusion + inputs[:, :1, None]

    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        amplitude = sample_joint([self.amplitude], n, generator)
        profile = torch.sin(math.pi * self.grid / 2)
        return (amplitude * profile).unsqueeze(1)
