"""Recorded inputs: signals u(t) that drive a model, as samples read linearly between them.

A physics model declares ``input_names`` (the pendulum: ``drive``, an angular acceleration); its
field then receives each input's value at the solve's time. The signals of a batch are
``values`` (B, T_u, I): one row per trajectory, sampled at ``times`` (T_u,) that the batch
shares; between two samples a signal is linear, before the first and after the last it holds
its end value. They come from one of two sources, a :class:`SignalSource`:

- :class:`Recorded`: a file's recorded inputs (a ``drive`` column), its missing samples filled
  linearly between the recorded ones (:func:`filled`); a simulation draws the signals of a
  recorded trajectory (the simulations of a marginal fit take the measured file's inputs).
- an :class:`InputProcess` such as :class:`SumOfSines`, declared for a generated DGP, which draws
  a new signal per trajectory, so that tests and benchmarks need no file.

A model with no source is not driven: its inputs are zero and its solve is the undriven one.
"""

from __future__ import annotations

import hashlib
import math
from abc import ABC, abstractmethod

import numpy as np
import torch
from torch import Tensor

from otgb.errors import InputError
from otgb.physics.arguments import RecordsInitArgs, invalid
from otgb.physics.priors import Prior, check_prior


def value_at(times: Tensor, values: Tensor, t: Tensor) -> Tensor:
    """Signals (B, T_u, I) sampled at ``times`` (T_u,), read at each row's time ``t`` (B,): (B, I), linear between
    samples and held at the ends."""
    t = t.to(times.dtype).clamp(times[0], times[-1])
    right = torch.searchsorted(times, t.contiguous()).clamp(1, len(times) - 1)
    left = right - 1
    weight = ((t - times[left]) / (times[right] - times[left])).to(values.dtype)[:, None]
    rows = torch.arange(len(values), device=values.device)
    return values[rows, left] + weight * (values[rows, right] - values[rows, left])


def filled(times: Tensor, values: Tensor) -> Tensor:
    """Signals (N, T, I) at ``times`` (T,) with their missing samples (NaN) filled linearly between the recorded ones
    (held at the ends). A signal with no recorded sample is an error for the caller to name."""
    out = values.clone()
    for n, i in zip(*torch.nonzero(torch.isnan(values).any(1), as_tuple=True)):
        known = ~torch.isnan(values[n, :, i])
        line = np.interp(times.double().numpy(), times[known].double().numpy(), values[n, known, i].double().numpy())
        out[n, :, i] = torch.from_numpy(line).to(values)
    return out


class SignalSource(ABC):
    """Where a model's input signals come from: ``times`` (T_u,) and :meth:`sample` of n rows (n, T_u, I)."""

    @abstractmethod
    def signal_times(self, horizon: float, step: float) -> Tensor:
        """The sample times (T_u,) of this source's signals for a model solved to ``horizon`` with ``step``."""

    @abstractmethod
    def sample(self, n: int, times: Tensor, generator: torch.Generator) -> Tensor:
        """n signals (n, T_u, I) at ``times``."""


class Recorded(SignalSource):
    """The signals a file recorded, (N, T_u, I) at ``times`` (T_u,), missing samples filled (:func:`filled`); a draw
    takes whole recorded rows, uniformly with replacement."""

    def __init__(self, times: Tensor, values: Tensor) -> None:
        self.times, self.values = times.float(), filled(times, values).float()

    def signal_times(self, horizon: float, step: float) -> Tensor:
        return self.times

    def sample(self, n: int, times: Tensor, generator: torch.Generator) -> Tensor:
        rows = torch.randint(len(self.values), (n,), generator=generator)
        return self.values[rows]

    def rows(self, index: Tensor) -> Recorded:
        """The recorded signals of the trajectories ``index`` only (a file's training part)."""
        part = Recorded.__new__(Recorded)
        part.times, part.values = self.times, self.values[index]
        return part

    def __repr__(self) -> str:
        digest = hashlib.sha256(self.values.numpy().tobytes()).hexdigest()[:12]
        return f"Recorded({tuple(self.values.shape)} signals at {len(self.times)} times, {digest})"


class InputProcess(RecordsInitArgs, SignalSource):
    """A random process that draws one input signal per trajectory, for a generated DGP (``drive: SumOfSines``).

    Its signals are sampled at a third of the solver step, where RK4's stages fall, so that reading them linearly
    between samples gives the process's own values at every stage."""

    def signal_times(self, horizon: float, step: float) -> Tensor:
        count = math.ceil(horizon / (step / 3) - 1e-6) + 1
        return torch.arange(count, dtype=torch.float32) * (step / 3)

    def sample(self, n: int, times: Tensor, generator: torch.Generator) -> Tensor:
        return self.draw(n, times.double(), generator).float()[..., None]

    @abstractmethod
    def draw(self, n: int, times: Tensor, generator: torch.Generator) -> Tensor:
        """n signals (n, T_u) at ``times``."""


class SumOfSines(InputProcess):
    """u(t) = sum over k of a_k sin(2 pi f_k t + phi_k), a new (a_k, f_k, phi_k) per trajectory, phi_k ~ U(0, 2 pi).

    Args:
        amplitude: prior of each sine's amplitude a_k (the input's unit).
        frequency: prior of each sine's frequency f_k (cycles per unit of time).
        terms: the number of sines.
    """

    def __init__(self, amplitude: Prior, frequency: Prior, terms: int = 2) -> None:
        if isinstance(terms, bool) or not isinstance(terms, int) or terms < 1:
            raise invalid(self, "terms", terms, "an integer >= 1")
        self.amplitude, self.frequency = check_prior(self, "amplitude", amplitude), check_prior(self, "frequency", frequency)
        self.terms = terms

    def draw(self, n: int, times: Tensor, generator: torch.Generator) -> Tensor:
        shape = (n, self.terms)
        amplitude = self.amplitude.sample(n * self.terms, generator).reshape(shape).double()
        frequency = self.frequency.sample(n * self.terms, generator).reshape(shape).double()
        phase = 2 * math.pi * torch.rand(shape, generator=generator, dtype=torch.float64)
        angle = 2 * math.pi * frequency[:, :, None] * times + phase[:, :, None]
        return (amplitude[:, :, None] * torch.sin(angle)).sum(1)


def check_source(owner: object, name: str, source: object) -> None:
    """``source`` may drive the input ``name`` of ``owner``: an :class:`InputProcess` or None."""
    if source is not None and not isinstance(source, InputProcess):
        raise invalid(owner, name, source, "an input process such as otgb.physics.SumOfSines, or null (not driven)")


def check_signals(where: str, signals: Tensor, batch: int, times: Tensor, n_inputs: int) -> None:
    if tuple(signals.shape) != (batch, len(times), n_inputs):
        raise InputError(
            f"{where}: signals have shape {tuple(signals.shape)}, expected ({batch}, {len(times)}, {n_inputs}): one row of "
            "recorded inputs per trajectory at the model's signal times"
        )
