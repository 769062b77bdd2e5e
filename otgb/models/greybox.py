"""The deep grey-box map T_phi(x; theta, z) (paper eq. phys-neural-ode).

    y(0) = x(0),   dy/dt = f_p(y, theta, u(t)) + f_phi(y, u(t), theta, z),

solved with the physics model's own fixed-step solver; z is drawn once per trajectory and
held constant along the solve. u(t) are the recorded inputs of a driven model
(:mod:`otgb.physics.signals`): f_phi sees their values beside the state, as more channels.

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
        self.n_inputs = len(physics.input_names) if physics.is_driven else 0
        channels, *grid = physics.state_shape
        self.correction = correction(
            (channels + self.n_inputs, *grid), tuple(physics.correction_shape), physics.theta_dim + z_dim
        )

    def forward(self, x: Tensor, initial_state: Tensor, theta: Tensor, z: Tensor, signals: Tensor | None = None) -> Tensor:
        """Generated observed trajectories (B, T, *obs) from x0 (B, *state), theta (B, P), z (B, z_dim) and the input
        ``signals`` (B, T_u, I) of a driven model.

        ``x`` (the source simulation) is part of the map interface; the grey-box only needs
        its initial state.
        """
        states = self.solve(initial_state, theta, z, signals)
        trajectories = self.physics.observe(states)
        raise_if_diverged(trajectories, "GreyBoxODE", theta)
        return trajectories

    def vector_field(self, state: Tensor, theta: Tensor, cond: Tensor, inputs: Tensor | None = None) -> Tensor:
        known = self.physics.vector_field(state, theta, inputs=inputs)
        return self.physics.add_correction(known, self.correction(self.with_inputs(state, inputs), cond))

    def conditioned_field(self, state: Tensor, theta: Tensor, *parts: Tensor, inputs: Tensor | None = None) -> Tensor:
        """:meth:`vector_field` with the condition's share of f_phi computed beforehand (``correction.condition``)."""
        known = self.physics.vector_field(state, theta, inputs=inputs)
        return self.physics.add_correction(known, self.correction.conditioned(self.with_inputs(state, inputs), *parts))

    def with_inputs(self, state: Tensor, inputs: Tensor | None) -> Tensor:
        """What f_phi sees: the state (B, C, *grid), and for a driven model the inputs' values (B, I) as I more channels
        (constant over a field's grid; zero where the solve has none)."""
        if not self.n_inputs:
            return state
        if inputs is None:
            inputs = state.new_zeros(len(state), self.n_inputs)
        grid = state.shape[2:]
        return torch.cat([state, inputs.reshape(*inputs.shape, *[1] * len(grid)).expand(*inputs.shape, *grid)], dim=1)

    def solve(self, initial_state: Tensor, theta: Tensor, z: Tensor, signals: Tensor | None = None) -> Tensor:
        """States (B, T, *state) of the corrected model.

        A correction that splits off what the condition contributes (``condition(cond)`` and
        ``conditioned(u, *parts)``, as otgb's conditional networks do) has it computed once per
        solve instead of at every stage: z and theta are constant along a trajectory.
        """
        cond = torch.cat([theta, z], dim=1)
        if hasattr(self.correction, "condition"):
            parts = self.correction.condition(cond)
            return self.physics.solve(self.conditioned_field, initial_state, theta, *parts, signals=signals)
        return self.physics.solve(self.vector_field, initial_state, theta, cond, signals=signals)

    @torch.no_grad()
    def components(self, initial_state: Tensor, theta: Tensor, z: Tensor, signals: Tensor | None = None) -> dict[str, Tensor]:
        """Each component of dy/dt evaluated along the generated solution.

        Returns ``states`` (B, T, *state), ``physics`` = f_p on them (B, T, *state),
        ``correction`` = f_phi on them (B, T, *correction_shape) and, for a driven model, ``inputs``
        (B, T, I), the inputs' values at the states' times.
        """
        states = self.solve(initial_state, theta, z, signals)
        batch, steps = states.shape[:2]
        flat = states.flatten(0, 1)
        repeat = lambda v: v.repeat_interleave(steps, dim=0)  # noqa: E731
        theta_r, cond_r = repeat(theta), repeat(torch.cat([theta, z], dim=1))
        inputs = None if signals is None else self.physics.inputs_along(signals)
        flat_inputs = None if inputs is None else inputs.flatten(0, 1)
        physics = self.physics.vector_field(flat, theta_r, inputs=flat_inputs).reshape(batch, steps, *self.physics.state_shape)
        correction = self.correction(self.with_inputs(flat, flat_inputs), cond_r)
        out = {
            "states": states,
            "physics": physics,
            "correction": correction.reshape(batch, steps, *self.physics.correction_shape),
        }
        return out if inputs is None else {**out, "inputs": inputs}
