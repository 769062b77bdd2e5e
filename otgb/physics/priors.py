"""Scalar priors that sample with an explicit ``torch.Generator``.

``torch.distributions`` cannot take a generator, and every otgb data set must be a pure
function of its seed, so the few distributions the physics layer needs live here.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


class Prior:
    """A distribution over one scalar; ``sample(n, generator)`` returns shape (n,)."""

    def sample(self, n: int, generator: torch.Generator) -> Tensor:
        raise NotImplementedError

    @property
    def is_constant(self) -> bool:
        return False


class Constant(Prior):
    """The point mass at ``value``."""

    def __init__(self, value: float) -> None:
        self.value = float(value)

    def sample(self, n: int, generator: torch.Generator) -> Tensor:
        return torch.full((n,), self.value)

    @property
    def is_constant(self) -> bool:
        return True

    def __repr__(self) -> str:
        return f"Constant({self.value!r})"


class Uniform(Prior):
    """U(low, high)."""

    def __init__(self, low: float, high: float) -> None:
        if not high > low:
            raise ValueError(f"Uniform prior needs low < high, got low={low}, high={high}")
        self.low, self.high = float(low), float(high)

    def sample(self, n: int, generator: torch.Generator) -> Tensor:
        return self.low + (self.high - self.low) * torch.rand(n, generator=generator)

    def __repr__(self) -> str:
        return f"Uniform({self.low!r}, {self.high!r})"


class Choice(Prior):
    """One of ``values``, each equally likely (a mixture of point masses)."""

    def __init__(self, values: Sequence[float]) -> None:
        if len(values) == 0:
            raise ValueError("Choice prior needs at least one value")
        self.values = [float(v) for v in values]

    def sample(self, n: int, generator: torch.Generator) -> Tensor:
        index = torch.randint(len(self.values), (n,), generator=generator)
        return torch.tensor(self.values)[index]

    @property
    def is_constant(self) -> bool:
        return len(set(self.values)) == 1

    def __repr__(self) -> str:
        return f"Choice({self.values!r})"
