"""The pendulum (paper, Damped Pendulum): f_p is the frictionless pendulum.

State (angle, angular velocity); d angle/dt = velocity, d velocity/dt = -omega^2 sin(angle).
Only the angle is observed. theta = (omega,). The grey-box correction acts on the
acceleration only.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from otgb.physics.base import PhysicsModel, Term, check_range, uniform_box


class Pendulum(PhysicsModel):
    """Frictionless pendulum observed through its angle, 50 points at dt = 0.1 by default.

    Args:
        omega_range: prior U(low, high) of the natural frequency omega.
        angle_range: prior U(low, high) of the initial angle; the initial velocity is 0.
    """

    state_shape = (2,)
    obs_shape = (1,)
    theta_names = ("omega",)

    def __init__(
        self,
        omega_range: tuple[float, float] = (0.785, 3.14),
        angle_range: tuple[float, float] = (-1.57, 1.57),
        dt: float = 0.1,
        n_obs: int = 50,
        step_size: float | None = None,
        method: str = "rk4",
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        super().__init__(dt, n_obs, True, step_size, method, hidden_effect)
        self.omega_range = check_range("Pendulum.omega_range", omega_range)
        self.angle_range = check_range("Pendulum.angle_range", angle_range)

    def field(self, state: Tensor, theta: Tensor) -> Tensor:
        angle, velocity = state[:, 0], state[:, 1]
        omega = theta[:, 0]
        return torch.stack([velocity, -(omega**2) * torch.sin(angle)], dim=1)

    def observe(self, state: Tensor) -> Tensor:
        return state[..., :1]

    def sample_theta(self, n: int, generator: torch.Generator) -> Tensor:
        return uniform_box([self.omega_range[0]], [self.omega_range[1]], n, generator)

    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        angle = uniform_box([self.angle_range[0]], [self.angle_range[1]], n, generator)
        return torch.cat([angle, torch.zeros_like(angle)], dim=1)

    @property
    def correction_shape(self) -> tuple[int, ...]:
        return (1,)

    def add_correction(self, dstate: Tensor, correction: Tensor) -> Tensor:
        return dstate + torch.cat([torch.zeros_like(correction), correction], dim=1)

    def energy(self, state: Tensor, theta: Tensor) -> Tensor:
        """Mechanical energy per unit inertia, 0.5 v^2 + omega^2 (1 - cos angle); (..., ) shape."""
        omega = theta[:, 0].reshape(-1, *([1] * (state.dim() - 2)))
        return 0.5 * state[..., 1] ** 2 + omega**2 * (1 - torch.cos(state[..., 0]))

    def extra_repr(self) -> str:
        return (
            f"omega_range={self.omega_range}, angle_range={self.angle_range}, dt={self.dt}, "
            f"n_obs={self.n_obs}, step_size={self.step_size}, method={self.method!r}"
        )
