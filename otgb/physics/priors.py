"""Scalar priors that sample with an explicit ``torch.Generator``.

``torch.distributions`` cannot take a generator, and every otgb data set must be a pure
function of its seed, so the few distributions the physics layer needs live here. A prior is
a configurable object: ``{class_path: otgb.physics.Uniform, init_args: {low: 1, high: 2}}``
in a config; its repr shows its arguments (data sets are cached under it).
"""

from __future__ import annotations

import math
import sys
from abc import ABC, abstractmethod
from collections.abc import Sequence
from types import FrameType, ModuleType

import torch
from jsonargparse import lazy_instance
from jsonargparse import typing as jsonargparse_typing
from torch import Tensor

from otgb.physics.arguments import RecordsInitArgs, invalid


class Prior(RecordsInitArgs, ABC):
    """A distribution over one scalar, given by its quantile function (inverse CDF).

    ``sample(n, generator)`` returns shape (n,); a constant prior draws no random numbers.
    """

    @abstractmethod
    def quantile(self, u: Tensor) -> Tensor:
        """The values at cumulative probabilities ``u`` in [0, 1), same shape as ``u``."""

    @property
    def is_constant(self) -> bool:
        return False

    @property
    def kind(self) -> str:
        """The prior's class as configs name it (``Uniform``, ``Normal``, ...), also for a class's default instance
        (a lazily built subclass of it)."""
        return next(c.__name__ for c in type(self).__mro__ if c.__module__ == __name__)

    def sample(self, n: int, generator: torch.Generator) -> Tensor:
        if self.is_constant:
            return self.quantile(torch.zeros(n))
        return self.quantile(torch.rand(n, generator=generator))


class Constant(Prior):
    """The point mass at ``value``.

    Args:
        value: the value every draw takes.
    """

    def __init__(self, value: float) -> None:
        if not _finite(value):
            raise invalid(self, "value", value, "a finite number")
        self.value = float(value)

    def quantile(self, u: Tensor) -> Tensor:
        return torch.full_like(u, self.value)

    @property
    def is_constant(self) -> bool:
        return True


class Uniform(Prior):
    """U(low, high).

    Args:
        low: lower end of the interval.
        high: upper end of the interval, above ``low``.
    """

    def __init__(self, low: float, high: float) -> None:
        if not (_finite(low) and _finite(high) and high > low):
            raise invalid(self, "(low, high)", (low, high), "finite numbers with low < high")
        self.low, self.high = float(low), float(high)

    def quantile(self, u: Tensor) -> Tensor:
        low, high = torch.tensor(self.low), torch.tensor(self.high)
        return low + (high - low) * u


class Normal(Prior):
    """N(mean, std^2).

    Args:
        mean: the mean.
        std: the standard deviation, positive.
    """

    def __init__(self, mean: float, std: float) -> None:
        if not (_finite(mean) and _finite(std) and std > 0):
            raise invalid(self, "(mean, std)", (mean, std), "finite numbers with std > 0")
        self.mean, self.std = float(mean), float(std)

    def quantile(self, u: Tensor) -> Tensor:
        u = u.clamp(1e-7, 1 - 1e-7)  # the tails' inverse CDF is finite
        return self.mean + self.std * math.sqrt(2) * torch.erfinv(2 * u - 1)


class Choice(Prior):
    """One of ``values``, each equally likely (a mixture of point masses).

    Args:
        values: the possible values, at least one.
    """

    def __init__(self, values: Sequence[float]) -> None:
        if isinstance(values, (str, bytes)) or len(values) == 0 or not all(_finite(v) for v in values):
            raise invalid(self, "values", values, "a non-empty list of finite numbers")
        self.values = [float(v) for v in values]

    def quantile(self, u: Tensor) -> Tensor:
        index = (u * len(self.values)).long().clamp(max=len(self.values) - 1)
        return torch.tensor(self.values)[index]

    def sample(self, n: int, generator: torch.Generator) -> Tensor:
        """Uniform indices from ``torch.randint`` (the draws of hidden-effect terms since the first data sets)."""
        index = torch.randint(len(self.values), (n,), generator=generator)
        return torch.tensor(self.values)[index]

    @property
    def is_constant(self) -> bool:
        return len(set(self.values)) == 1


def default_prior(cls: type[Prior], **kwargs: float) -> Prior:
    """A Prior as a constructor's default, shown by ``--print_config`` as its class_path and init_args.

    It is jsonargparse's ``lazy_instance``, told its caller directly: the library finds its caller
    through ``inspect.stack()``, which reads the source of every frame above it, and inside the
    import chain of ``otgb`` that took 0.13 s a call, 0.9 s of every command's start.
    """
    real = jsonargparse_typing.inspect
    jsonargparse_typing.inspect = _CallerOnlyStack(sys._getframe(1), real)
    try:
        return lazy_instance(cls, **kwargs)
    finally:
        jsonargparse_typing.inspect = real


class _CallerOnlyStack:
    """The ``inspect`` module as jsonargparse's ``lazy_instance`` sees it: a stack of the caller alone."""

    def __init__(self, caller: FrameType, inspect: ModuleType) -> None:
        self._caller, self._inspect = caller, inspect

    def stack(self) -> list:
        return [None, self._inspect.FrameInfo(self._caller, "", 0, "", None, None)]

    def __getattr__(self, name: str) -> object:
        return getattr(self._inspect, name)


def sample_joint(priors: Sequence[Prior], n: int, generator: torch.Generator) -> Tensor:
    """(n, len(priors)) independent draws: one (n, k) uniform draw for the k random priors.

    Each random prior maps its column through its quantile function; constant priors draw
    nothing. One joint draw (not one per prior) keeps the generator's order of a box of
    uniforms, ``low + (high - low) * torch.rand(n, k)``.
    """
    random = [i for i, prior in enumerate(priors) if not prior.is_constant]
    u = torch.rand(n, len(random), generator=generator) if random else None
    columns = [
        prior.quantile(u[:, random.index(i)] if i in random else torch.zeros(n))  # type: ignore[index]
        for i, prior in enumerate(priors)
    ]
    return torch.stack(columns, dim=-1) if columns else torch.zeros(n, 0)


def _finite(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_prior(owner: object, name: str, value: object) -> Prior:
    """``value`` if it is a Prior, else an InputError naming ``owner``'s argument ``name``."""
    if not isinstance(value, Prior):
        raise invalid(owner, name, value, "a Prior (otgb.physics.Uniform, Normal, Constant or Choice)")
    if hasattr(value, "lazy_get_init_data"):
        value.quantile(torch.zeros(0))  # a jsonargparse lazy_instance default: its first method call runs its __init__
    return value
