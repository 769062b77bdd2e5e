"""The prior families a fitted coefficient takes, in one place: their names (simplest first), whether one varies
between trajectories, the prior a centre and a width make in each, a prior's centre and width, and the standard draws that
centre + width * noise maps to coefficients.

- ``constant``: c (the effect is the same in every trajectory);
- ``uniform``: U(c - w, c + w); ``normal``: N(c, w^2); ``two_point``: c - w or c + w, equally likely (an effect that
  takes one of two values, as two kinds of a part or two operating conditions give).
"""

from __future__ import annotations

import torch
from torch import Tensor

from otgb.physics.priors import Choice, Constant, Normal, Prior, Uniform

CONSTANT, UNIFORM, NORMAL, TWO_POINT = "constant", "uniform", "normal", "two_point"
FAMILIES = (CONSTANT, UNIFORM, NORMAL, TWO_POINT)  # simplest first
SPREAD_FAMILIES = (UNIFORM, NORMAL)  # the families a spread the data exclude is stated in, the first offered first


def varies(family: str) -> bool:
    """Whether a coefficient of ``family`` varies between trajectories (every family but the constant)."""
    return family != CONSTANT


def prior(family: str, centre: float, width: float) -> Prior:
    """The prior of ``family`` around ``centre`` with half-width (uniform, two-point) or standard deviation (normal)
    ``width`` (the constant ignores it)."""
    if family == CONSTANT:
        return Constant(centre)
    if family == UNIFORM:
        return Uniform(centre - width, centre + width)
    if family == TWO_POINT:
        return Choice([centre - width, centre + width])
    return Normal(centre, width)


def centre(fitted: Prior) -> float:
    """The centre c of a fitted prior: the constant c, U(c - w, c + w), N(c, w^2) or {c - w, c + w}."""
    if isinstance(fitted, Constant):
        return fitted.value
    if isinstance(fitted, Uniform):
        return (fitted.low + fitted.high) / 2
    if isinstance(fitted, Normal):
        return fitted.mean
    if isinstance(fitted, Choice):
        return sum(fitted.values) / len(fitted.values)
    raise TypeError(f"centre: a Constant, Uniform, Normal or Choice prior, got {type(fitted).__name__}")


def spread(fitted: Prior) -> float:
    """The width w of a fitted prior that varies: U(c - w, c + w)'s and {c - w, c + w}'s half-width, N(c, w^2)'s
    standard deviation."""
    if isinstance(fitted, Choice):
        return (max(fitted.values) - min(fitted.values)) / 2
    return (fitted.high - fitted.low) / 2 if isinstance(fitted, Uniform) else fitted.std


def standard_noise(family: str, shape: tuple[int, ...], generator: torch.Generator) -> Tensor:
    """Draws that a prior family's centre + width * noise maps to coefficients: N(0, 1) (normal), -1 or 1 equally
    likely (two-point) or U(-1, 1)."""
    if family == NORMAL:
        return torch.randn(shape, generator=generator)
    uniform = 2 * torch.rand(shape, generator=generator) - 1
    return torch.where(uniform < 0, -1.0, 1.0) if family == TWO_POINT else uniform
