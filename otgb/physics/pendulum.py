"""The pendulum (paper, Damped Pendulum): f_p is the frictionless pendulum.

State (angle, angular velocity); d angle/dt = velocity, d velocity/dt = -omega^2 sin(angle) + drive.
Only the angle is observed. theta = (omega,). ``drive`` is a recorded input, an angular
acceleration (a torque per unit inertia): zero unless a file records it or a process draws it.
The grey-box correction acts on the acceleration only.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from otgb.physics.base import PhysicsModel, Term
from otgb.physics.priors import Constant, Prior, Uniform, default_prior
from otgb.physics.signals import InputProcess


class Pendulum(PhysicsModel):
    """Frictionless pendulum observed through its angle, 50 points at dt = 0.1 by default.

    Args:
        omega: prior of the natural frequency omega (rad/s), drawn once per trajectory.
        angle: prior of the initial angle (rad).
        velocity: prior of the initial angular velocity (rad/s); at rest by default.
        drive: the process a generated DGP draws the drive (rad/s^2) from, e.g. ``otgb.physics.SumOfSines``; None:
            no drive, unless the measured file records a ``drive`` column.
        dt: time between two observations.
        n_obs: number of observations, the first at t = 0.
        step_size: solver step, a divisor of dt; defaults to dt.
        method: a torchdiffeq fixed-step method ("rk4", "euler", "midpoint", ...).
        hidden_effect: terms added to f_p; empty for f_p (the data module adds the DGP's).
    """

    state_names = ("angle", "velocity")
    observed = ("angle",)
    theta_names = ("omega",)
    input_names = ("drive",)
    angle_names = ("angle",)
    velocity_names = ("velocity",)
    units = {"t": "s", "angle": "rad", "velocity": "rad/s", "omega": "rad/s", "drive": "rad/s^2"}

    def __init__(
        self,
        omega: Prior = default_prior(Uniform, low=0.785, high=3.14),
        angle: Prior = default_prior(Uniform, low=-1.57, high=1.57),
        velocity: Prior = default_prior(Constant, value=0.0),
        drive: InputProcess | None = None,
        dt: float = 0.1,
        n_obs: int = 50,
        step_size: float | None = None,
        method: str = "rk4",
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        super().__init__(dt, n_obs, True, step_size, method, hidden_effect)

    def field(self, state: Tensor, theta: Tensor, inputs: Tensor | None = None) -> Tensor:
        angle, velocity = state[:, 0], state[:, 1]
        omega = theta[:, 0]
        acceleration = -(omega**2) * torch.sin(angle)
        return torch.stack([velocity, acceleration if inputs is None else acceleration + inputs[:, 0]], dim=1)

    @property
    def correction_shape(self) -> tuple[int, ...]:
        return (1,)

    def add_correction(self, dstate: Tensor, correction: Tensor) -> Tensor:
        return dstate + torch.cat([torch.zeros_like(correction), correction], dim=1)

    def energy(self, state: Tensor, theta: Tensor) -> Tensor:
        """Mechanical energy per unit inertia, 0.5 v^2 + omega^2 (1 - cos angle); (..., ) shape."""
        omega = theta[:, 0].reshape(-1, *([1] * (state.dim() - 2)))
        return 0.5 * state[..., 1] ** 2 + omega**2 * (1 - torch.cos(state[..., 0]))
