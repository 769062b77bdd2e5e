"""Finite-difference stencils on uniform grids, batched over leading dimensions.

Boundaries: ``"dirichlet"`` pads with zero ghost points (the field vanishes one step outside
the grid); ``"periodic"`` wraps around. Spatial axes are the trailing ``dims`` axes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def _shifted(u: Tensor, axis: int, step: int, boundary: str) -> Tensor:
    """u at index i + step along ``axis`` (a negative axis), with the boundary's ghost values."""
    if boundary == "periodic":
        return torch.roll(u, shifts=-step, dims=axis)
    pad = [0, 0] * (-axis - 1) + ([0, 1] if step > 0 else [1, 0])
    padded = F.pad(u, pad)
    length = u.shape[axis]
    start = 1 if step > 0 else 0
    return padded.narrow(axis, start, length)


def central_difference(u: Tensor, dx: float, boundary: str, axis: int = -1) -> Tensor:
    """du/ds ~ (u[i+1] - u[i-1]) / (2 dx) along ``axis``."""
    return (_shifted(u, axis, 1, boundary) - _shifted(u, axis, -1, boundary)) / (2 * dx)


def second_difference(u: Tensor, dx: float, boundary: str, axis: int = -1) -> Tensor:
    """d^2u/ds^2 ~ (u[i+1] - 2 u[i] + u[i-1]) / dx^2 along ``axis``."""
    return (_shifted(u, axis, 1, boundary) - 2 * u + _shifted(u, axis, -1, boundary)) / dx**2


def laplacian(u: Tensor, dx: float, boundary: str, dims: int) -> Tensor:
    """Sum over the last ``dims`` axes of (u[i+1] - 2 u[i] + u[i-1]) / dx^2 (the 3/5-point stencil)."""
    out = -2 * dims * u
    for axis in range(-dims, 0):
        out = out + _shifted(u, axis, 1, boundary) + _shifted(u, axis, -1, boundary)
    return out / dx**2
