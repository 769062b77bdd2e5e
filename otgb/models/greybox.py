"""The deep grey-box map T_phi(x; theta, z) (paper eq. phys-neural-ode).

    y(0) = x(0),   dy/dt = f_p(y, theta) + f_phi(y, theta, z),

solved with the physics model's own fixed-step solver; z is drawn once per trajectory and
held constant along the solve.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from otgb.physics.base import PhysicsModel, raise_if_diverged

CorrectionFactory = Callable[[tuple, tuple, int], nn.Module]


class GreyBoxODE(nn.Module):
    """f_p plus a learned correction f_phi, integrated like the source simulations.

    Args:
        physics: the incomplete model f_p (its terms, if any, are part of the known physics).
        z_dim: size of the latent z (0 for a deterministic one-to-one map).
        correction: builds f_phi from (state_shape, correction_shape, cond_dim); called with
            cond_dim = theta_dim + z_dim. f_phi(state, cond) returns the correction's shape.
    """

    def __init__(self, physics: PhysicsModel, z_dim: int, correction: CorrectionFactory) -> None:
        super().__init__()
        self.physics = physics
        self.z_dim = z_dim
        self.correction = correction(tuple(physics.state_shape), tuple(physics.correction_shape), physics.theta_dim + z_dim)

    def forward(self, x: Tensor, initial_state: Tensor, theta: Tensor, z: Tensor) -> Tensor:
        """Generated observed trajectories (B, T, *obs) from x0 (B, *state), theta (B, P), z (B, z_dim).

        ``x`` (the source simulation) is part of the map interface; the grey-box only needs
        its initial state.
        """
        states = self.solve(initial_state, theta, z)
        trajectories = self.physics.observe(states)
        raise_if_diverged(trajectories, "GreyBoxODE", theta)
        return trajectories

    def vector_field(self, state: Tensor, theta: Tensor, cond: Tensor) -> Tensor:
        return self.physics.add_correction(self.physics.vector_field(state, theta), self.correction(state, cond))

    def conditioned_field(self, state: Tensor, theta: Tensor, *parts: Tensor) -> Tensor:
        """:meth:`vector_field` with the condition's share of f_phi computed beforehand (``correction.condition``)."""
        return self.physics.add_correction(self.physics.vector_field(state, theta), self.correction.conditioned(state, *parts))

    def solve(self, initial_state: Tensor, theta: Tensor, z: Tensor) -> Tensor:
        """States (B, T, *state) of the corrected model.

        A correction that splits off what the condition contributes (``condition(cond)`` and
        ``conditioned(u, *parts)``, as otgb's conditional networks do) has it computed once per
        solve instead of at every stage: z and theta are constant along a trajectory.
        """
        cond = torch.cat([theta, z], dim=1)
        if hasattr(self.correction, "condition"):
            return self.physics.solve(self.conditioned_field, initial_state, theta, *self.correction.condition(cond))
        return self.physics.solve(self.vector_field, initial_state, theta, cond)

    @torch.no_grad()
    def components(self, initial_state: Tensor, theta: Tensor, z: Tensor) -> dict[str, Tensor]:
        """Each component of dy/dt evaluated along the generated solution.

        Returns ``states`` (B, T, *state), ``physics`` = f_p on them (B, T, *state) and
        ``correction`` = f_phi on them (B, T, *correction_shape).
        """
        states = self.solve(initial_state, theta, z)
        batch, steps = states.shape[:2]
        flat = states.flatten(0, 1)
        repeat = lambda v: v.repeat_interleave(steps, dim=0)  # noqa: E731
        theta_r, cond_r = repeat(theta), repeat(torch.cat([theta, z], dim=1))
        physics = self.physics.vector_field(flat, theta_r).reshape(batch, steps, *self.physics.state_shape)
        correction = self.correction(flat, cond_r).reshape(batch, steps, *self.physics.correction_shape)
        return {"states": states, "physics": physics, "correction": correction}
