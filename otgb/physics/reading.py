"""A model's states read at any times inside its solve: cubic Hermite interpolation between steps.

The solver steps on its own grid t_k = k h. A time t inside step k (t_k <= t < t_k+1, s = (t - t_k) / h)
is read from the two step ends' states and derivatives (the vector field there):

    y(t) = h00(s) y_k + h h10(s) f_k + h01(s) y_k+1 + h h11(s) f_k+1,
    h00 = 2s^3 - 3s^2 + 1, h10 = s^3 - 2s^2 + s, h01 = -2s^3 + 3s^2, h11 = s^3 - s^2.

Its error is O(h^4), the order of the default RK4 solve itself (a linear interpolation's O(h^2)
would be the larger error at the default step). A time on a step end is that step's state.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

Field = Callable[..., Tensor]


def steps_to_cover(times: Tensor, step: float) -> int:
    """Solver steps from t = 0 whose last end reaches the last of ``times``."""
    return max(1, math.ceil(float(times.max()) / step - 1e-6))


def read_between_steps(states: Tensor, field: Field, args: Sequence[Tensor], step: float, times: Tensor) -> Tensor:
    """States (B, T, *state) at ``times`` (T,), from the solve's states at every step end ``states`` (B, K + 1, *state)
    and the vector field ``field(state, *args)`` (its arguments: one row per trajectory)."""
    last = states.shape[1] - 2
    position = times.to(states.device, torch.float64) / step
    k = position.floor().clamp(0, last).long()
    s = (position - k).clamp(0, 1).to(states.dtype)
    ends = torch.unique(torch.cat([k, k + 1]))  # the step ends any time needs: their derivatives only
    slot = torch.zeros(states.shape[1], dtype=torch.long, device=states.device)
    slot[ends] = torch.arange(len(ends), device=states.device)
    derivatives = _derivatives(states[:, ends], field, args)
    shape = (1, len(times), *([1] * (states.dim() - 2)))
    s = s.reshape(shape)
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    return (
        h00 * states[:, k]
        + (step * h10) * derivatives[:, slot[k]]
        + h01 * states[:, k + 1]
        + (step * h11) * derivatives[:, slot[k + 1]]
    )


def _derivatives(states: Tensor, field: Field, args: Sequence[Tensor]) -> Tensor:
    """field on every state of (B, K, *state), in one batched call: each trajectory's arguments repeated K times."""
    batch, count = states.shape[:2]
    repeated = [
        a.repeat_interleave(count, dim=0) if isinstance(a, Tensor) and a.dim() > 0 and len(a) == batch else a for a in args
    ]
    return field(states.flatten(0, 1), *repeated).reshape(states.shape)
