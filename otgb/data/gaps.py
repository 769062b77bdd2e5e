"""Missing measured values (NaN) where simulations meet measurements: both sides with the same gaps.

A measured trajectory is NaN wherever it has no value (:mod:`otgb.data.times`). Every comparison
of simulated or generated trajectories with measured ones treats a missing value the same way:

- the simulated sample takes the measured sample's missing-value patterns, row i the pattern of
  measured row i mod m (the measured rows are a random draw or a random order, so the patterns
  are independent of the simulations), and
- on both sides a missing value is then 0 (:func:`filled`).

The two samples then hold values at the same kind of places, so a whole-trajectory comparison
(the critic, an energy distance, the MMD, a classifier) compares the measured values with the
simulations' values at measured places and nothing else; where values are missing at random
(not because of what they would have been) it is unbiased. Statistics per time step use only
the trajectories measured there (:func:`observed`). A file with no missing value meets none of
this: every function returns its input.
"""

from __future__ import annotations

import torch
from torch import Tensor


def has_gaps(y: Tensor) -> bool:
    """Whether some value of ``y`` is missing (NaN)."""
    return bool(torch.isnan(y).any())


def observed(y: Tensor) -> Tensor:
    """Where ``y`` holds a value: a bool tensor of its shape."""
    return ~torch.isnan(y)


def filled(y: Tensor) -> Tensor:
    """``y`` with 0 for every missing value (``y`` itself when none is)."""
    return y.nan_to_num(nan=0.0) if has_gaps(y) else y


def with_gaps_of(simulated: Tensor, measured: Tensor, fill: float = float("nan")) -> Tensor:
    """``simulated`` (n, T, *obs) with ``fill`` (NaN: missing) where the measured trajectories (m, T, *obs) have no
    value: row i takes the pattern of measured row i mod m (``simulated`` itself when nothing is missing)."""
    if not has_gaps(measured):
        return simulated
    patterns = torch.isnan(measured)
    rows = torch.arange(len(simulated), device=patterns.device) % len(measured)
    return simulated.masked_fill(patterns[rows].to(simulated.device), fill)


def comparable(simulated: Tensor, measured: Tensor) -> tuple[Tensor, Tensor]:
    """Both samples as a whole-trajectory comparison sees them: ``simulated`` with the measured gaps, both 0 there
    (differentiable in ``simulated``: no NaN enters its graph)."""
    return with_gaps_of(simulated, measured, fill=0.0), filled(measured)
