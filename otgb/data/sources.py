"""Where the measured trajectories come from, and everything that follows from it for evaluation.

Two sources, one object each; the rest of otgb asks them and never branches on which one it has:

- :class:`GeneratedMeasurements`: a configured data-generating process (f_p plus
  ``data.hidden_effect``) generates the measured set and joint validation/test sets: the same
  inputs (x0, theta) through f_p and, ``draws_per_input`` times, through the process. Its
  evaluation is **joint**: each draw of the map is compared with the process on its own inputs.
- :class:`FileMeasurements`: a file of real measurements, split into train / validation / test
  parts. No process is known; the evaluation is **marginal**: the map's draws (inputs from the
  priors, or those the file recorded) against the held-out measurements, as two samples.
"""

from __future__ import annotations

import hashlib
from abc import ABC, abstractmethod
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from torch import Tensor

from otgb.data.files import read_measured
from otgb.data.measured import cache_key, cached, generate_joint, generate_measured, simulate_in_chunks, split_indices
from otgb.data.seeding import generator_for
from otgb.physics.base import PhysicsModel, Term
from otgb.physics.signals import Recorded

CACHE_FORMAT = 3  # 2: joint sets hold y_ref; 3: measured sets hold their inputs


class MeasurementSource(ABC):
    """The measured data of a run: its training set, its validation and test sets, and how they are compared."""

    mode: str  # "joint" or "marginal": named in the log at start-up and in every report
    reference_note: str  # what the Reference compares, for the reports: "over <reference_note>"
    measurement_noise: float = 0.0  # the sd of the white noise on the measured values; generated ones are noise-free

    def __init__(self, physics: PhysicsModel, seed: int) -> None:
        self.physics, self.seed = physics, seed

    @abstractmethod
    def describe(self) -> str:
        """What the evaluation compares, in one sentence."""

    @abstractmethod
    def measured_set(self) -> Tensor:
        """The measured trajectories the critic trains on (N, T, *obs)."""

    @abstractmethod
    def evaluation_set(self, split: str, n: int) -> dict[str, Tensor]:
        """x0, theta, f_p's x (n, T, *obs) and the measured y (n, M, T, *obs) of ``split`` ("val" or "test")."""

    @property
    @abstractmethod
    def recorded_inputs(self) -> tuple[str, ...]:
        """The map's inputs each measured trajectory comes with: a subset of ("theta", "x0")."""

    @property
    @abstractmethod
    def draws_per_input(self) -> int:
        """Measured draws M per evaluation input."""

    @property
    @abstractmethod
    def selection_metric(self) -> str:
        """The validation metric ``checkpoint.monitor: auto`` selects on."""

    @property
    @abstractmethod
    def pointwise_process(self) -> PhysicsModel | None:
        """The process whose draws pair one-to-one with the map's (pointwise errors, the true vector field), or None."""

    @property
    @abstractmethod
    def reference_on_same_inputs(self) -> bool:
        """Whether the Reference compares two draws on the same inputs (True) or two halves of the measurements."""

    def training_inputs(self) -> tuple[Tensor, Tensor] | None:
        """x0 and theta of each trajectory of :meth:`measured_set` where the measurements recorded both, else None."""
        return None

    records_signals = False  # whether each measured trajectory comes with its own recorded input signals

    def training_signals(self) -> Tensor | None:
        """The recorded input signals of each trajectory of :meth:`measured_set` (N, T_u, I), else None."""
        return None

    @property
    def draws_pair_with_inputs(self) -> bool:
        """Whether each measured draw belongs to its evaluation input (a figure per input) or not (distributions)."""
        return self.reference_on_same_inputs

    def evaluation_plan(self) -> dict[str, tuple[tuple[str, ...], bool, bool]]:
        """Metric-name prefix -> (conditioning inputs, paired, across halves): the comparisons every evaluation makes.

        Across halves (:func:`otgb.metrics.samples.across_halves`): the draws of an unpaired comparison were made
        on the measured trajectories' own recorded inputs (theta, x0 or input signals), so each is scored against
        the other half's measurements, never its own."""
        if self.reference_on_same_inputs:
            return {"": (("theta", "x0"), True, False)}
        plan = {"": ((), False, bool(self.recorded_inputs) or self.records_signals)}
        if self.recorded_inputs:
            plan["joint_"] = (tuple(self.recorded_inputs), True, False)
        return plan

    def facts(self) -> dict[str, Any]:
        """What produced the numbers, for the reports."""
        return {"mode": self.mode, "description": self.describe(), "reference_note": self.reference_note}

    @cached_property
    def identity(self) -> dict[str, str]:
        """Which measurements these are: ``what`` in words, ``data`` a digest of what decides them and ``key`` one of
        that and their training part. A checkpoint keeps it, so that a run that evaluates the checkpoint on other
        measurements, or on the same ones split differently, says so."""
        data = self._key_of_content()
        return {"what": self._what(), "data": data, "key": cache_key(data, self._key_of_training_part())}

    @abstractmethod
    def _what(self) -> str:
        """These measurements in a few words, for :attr:`identity`."""

    @abstractmethod
    def _key_of_content(self) -> str:
        """A digest of what decides these measurements, for :attr:`identity`."""

    def _key_of_training_part(self) -> str:
        """A digest of which of them the map trains on, for :attr:`identity` (generated ones: all)."""
        return ""

    @abstractmethod
    def sample_sizes(self, n_inputs: int, draws_per_input: int) -> str:
        """What a test report compares, with its sizes, e.g. "150 test inputs x 1 draw"."""

    @abstractmethod
    def as_file(self, folder: Path, trajectories: Tensor) -> str:
        """A file of these measurements that ``data.measured_path`` reads (``trajectories``: all parts, (N, T, *obs))."""


class GeneratedMeasurements(MeasurementSource):
    """Measurements generated by f_p plus ``hidden_effect`` (cached in ``cache_dir``); joint evaluation."""

    mode = "joint"

    def __init__(
        self, physics: PhysicsModel, hidden_effect: list[Term], n_measured: int, draws_per_input: int, seed: int,
        cache_dir: str, step_size: float | None = None,
    ) -> None:  # fmt: skip
        super().__init__(physics, seed)
        self.dgp = physics.with_hidden_effect(hidden_effect, step_size=step_size)
        self.n_measured, self._draws, self.cache_dir = n_measured, draws_per_input, cache_dir

    def describe(self) -> str:
        effect = ", ".join(type(t).__name__ for t in self.dgp.terms)
        return (
            f"measured data generated by a known DGP ({type(self.physics).__name__} + {effect}); the map is scored "
            "against DGP draws for the same inputs"
        )

    def _key(self, *parts: object) -> str:
        return cache_key(CACHE_FORMAT, repr(self.physics), repr(self.dgp), self.seed, *parts)

    def _what(self) -> str:
        effect = ", ".join(map(repr, self.dgp.terms))
        return f"measurements generated by the configured process ({type(self.physics).__name__} + {effect})"

    def _key_of_content(self) -> str:
        return cache_key(repr(self.dgp))

    def measured_set(self) -> Tensor:
        return self._generated()["y"]

    def _generated(self) -> dict[str, Tensor]:
        key = self._key("measured", self.n_measured)
        return cached(self.cache_dir, "measured", key, lambda: generate_measured(self.dgp, self.n_measured, self.seed))

    def evaluation_set(self, split: str, n: int) -> dict[str, Tensor]:
        key = self._key(split, n, self._draws)
        generate = lambda: generate_joint(self.physics, self.dgp, n, self._draws, self.seed, split)  # noqa: E731
        return cached(self.cache_dir, split, key, generate)

    @property
    def recorded_inputs(self) -> tuple[str, ...]:
        return ("theta", "x0")

    @property
    def draws_per_input(self) -> int:
        return self._draws

    @property
    def selection_metric(self) -> str:
        return "val/mmd" if self.dgp.is_stochastic else "val/abs_err"

    @property
    def pointwise_process(self) -> PhysicsModel | None:
        return None if self.dgp.is_stochastic else self.dgp

    @property
    def reference_on_same_inputs(self) -> bool:
        return True

    @property
    def reference_note(self) -> str:
        note = "random splits of two independent DGP draw sets on the same inputs"
        if self.dgp.is_stochastic:
            return note
        floor = "each metric's floor, 0 ± 0, or 0.5 for C2ST"
        return f"{note} (a deterministic DGP draws the same trajectories twice: its Reference is {floor})"

    def sample_sizes(self, n_inputs: int, draws_per_input: int) -> str:
        return f"{n_inputs} test inputs x {_draw_count(draws_per_input)}"

    def as_file(self, folder: Path, trajectories: Tensor) -> str:
        """The generated trajectories written to ``folder/measured.npz``: the next round must see them, not the DGP
        (which would add the named terms twice); a driven DGP's input signals go with them as ``u``, read at the
        observation times."""
        path = folder / "measured.npz"
        signals = self._generated().get("signals")
        inputs = {} if signals is None else {"u": self.dgp.inputs_along(signals).numpy()}
        np.savez(path, y=trajectories.numpy(), **inputs)
        return str(path.resolve())


class FileMeasurements(MeasurementSource):
    """Measurements read from ``path``, split into train / validation / test parts; marginal evaluation."""

    mode = "marginal"
    reference_note = (
        "random splits of the held-out measurements into two halves (half-size samples: the unbiased MMD^2_u and energy "
        "keep their mean, the biased paper-code MMD sits about twice as high as a full-size comparison at the noise floor)"
    )

    def __init__(
        self, physics: PhysicsModel, path: str, val_fraction: float, test_fraction: float, seed: int,
        measurement_noise: float = 0.0,
    ) -> None:  # fmt: skip
        self.path, self.file, self.measurement_noise = path, read_measured(path, physics), float(measurement_noise)
        physics = physics if self.file.times is None else physics.read_at(self.file.times)
        self.parts = split_indices(len(self.file), val_fraction, test_fraction, seed, path)
        self.recorded = None if self.file.u is None else Recorded(physics.observation_times(), self.file.u)
        # the simulations of training take the recorded inputs of the training part's trajectories
        super().__init__(physics if self.recorded is None else physics.driven_by(self.recorded.rows(self.parts["train"])), seed)

    def describe(self) -> str:
        sizes = " / ".join(f"{len(self.parts[p])} {p}" for p in ("train", "val", "test"))
        recorded = self.recorded_inputs
        drawn = [name for name in ("theta", "x0") if name not in recorded]
        parts = [f"{' and '.join(recorded)} as the file recorded {'it' if len(recorded) == 1 else 'them'}"] if recorded else []
        inputs = ", ".join(parts + ([f"{' and '.join(drawn)} drawn from the priors"] if drawn else []))
        sd = self.measurement_noise
        noise = f", the map's and f_p's with the measurements' white noise (sd {sd:.4g}) added" if sd else ""
        if self.recorded is not None:
            names = ", ".join(self.physics.input_names)
            noise += f"; every simulation is driven by a trajectory's recorded {names} (the held-out draws by their own)"
        halves = (
            " (the rows without recorded inputs across halves, as the Reference: the draws on one half's inputs against "
            "the other half's measurements, so that no draw meets its own measurement)"
            if recorded
            else ""
        )
        return (
            f"{len(self.file)} measured trajectories from {self.path} ({sizes}); no DGP is known: the map's draws "
            f"({inputs}) are compared with held-out measurements by two-sample metrics{halves}{noise}"
        )

    @property
    def records_signals(self) -> bool:
        return self.recorded is not None

    def training_signals(self) -> Tensor | None:
        return None if self.recorded is None else self.recorded.values[self.parts["train"]]

    def _what(self) -> str:
        return f"the measurements in {Path(self.path).resolve()}"

    def _key_of_content(self) -> str:
        return _digest(self.file.y)

    def _key_of_training_part(self) -> str:
        """Which trajectories are the training part: a split with another seed or other fractions would test the map on
        trajectories it trained on."""
        return _digest(self.parts["train"])

    def measured_set(self) -> Tensor:
        return self.file.y[self.parts["train"]]

    def evaluation_set(self, split: str, n: int) -> dict[str, Tensor]:
        """Held-out measurements y (n, 1, T, *obs) with the map's inputs (x0, theta) and f_p on them (x); inputs the
        file did not record are drawn from the priors (seeded by ``seed`` and the split). ``n`` is the part's size."""
        part = self.file.subset(self.parts[split])
        size, g = len(part), generator_for(self.seed, split, "inputs")
        x0 = part.x0 if part.x0 is not None else self.physics.sample_initial_state(size, g)
        theta = part.theta if part.theta is not None else self.physics.sample_theta(size, g)
        signals = None if self.recorded is None else self.recorded.values[self.parts[split]]
        x = simulate_in_chunks(self.physics, x0, theta, signals=signals)
        out = {"x0": x0, "theta": theta, "x": x, "y": part.y.unsqueeze(1)}
        return out if signals is None else {**out, "signals": signals}

    @property
    def recorded_inputs(self) -> tuple[str, ...]:
        return self.file.recorded_inputs

    def training_inputs(self) -> tuple[Tensor, Tensor] | None:
        if self.recorded_inputs != ("theta", "x0"):
            return None
        part = self.file.subset(self.parts["train"])
        return part.x0, part.theta

    @property
    def draws_per_input(self) -> int:
        return 1  # a file holds one measured trajectory per input

    @property
    def selection_metric(self) -> str:
        """The energy distance to the held-out measurements (smooth, unbiased, no bandwidth), or its joint version
        when the file recorded the map's inputs."""
        return "val/joint_energy" if self.recorded_inputs else "val/energy"

    @property
    def pointwise_process(self) -> PhysicsModel | None:
        return None

    @property
    def reference_on_same_inputs(self) -> bool:
        return False  # halves of the measurements have different inputs: unpaired

    def sample_sizes(self, n_inputs: int, draws_per_input: int) -> str:
        inputs = f"{n_inputs} inputs x {_draw_count(draws_per_input)}"
        return f"{n_inputs} held-out measured trajectories against the models' draws ({inputs})"

    def facts(self) -> dict[str, Any]:
        split = {part: len(index) for part, index in self.parts.items()}
        facts = {"measured_path": self.path, "split": split, "recorded_inputs": list(self.recorded_inputs)}
        facts["across_halves"] = self.evaluation_plan()[""][2]
        return {**super().facts(), **facts, "measurement_noise": self.measurement_noise}

    def as_file(self, folder: Path, trajectories: Tensor) -> str:
        return str(Path(self.path).resolve())


def _digest(tensor: Tensor) -> str:
    """A digest of a tensor's values."""
    return hashlib.sha256(tensor.detach().cpu().contiguous().numpy().tobytes()).hexdigest()[:16]


def _draw_count(n: int) -> str:
    """A number of draws in words: 1 draw, 10 draws."""
    return f"{n} draw{'' if n == 1 else 's'}"
