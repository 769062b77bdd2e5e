"""A discovery's result as a person and a program read it: the verdict, the named terms, the augmented physics, the
gap before and after; rendered as a terminal table (:meth:`DiscoveryResult.print`) or written as the report's files
(:meth:`DiscoveryResult.write`)."""

from __future__ import annotations

import copy
import sys
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from torch import Tensor

from otgb.analysis.components import to_json
from otgb.data.sources import MeasurementSource
from otgb.discovery.details import GAP_ROWS
from otgb.discovery.prior_text import distribution_text
from otgb.discovery.record import Discovery
from otgb.discovery.report import augmented_config, report_dict, write_augmented, write_report
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel


@dataclass(frozen=True)
class NamedTerm:
    """A term discovery named and kept.

    Args:
        name: Its physical name ("viscous friction").
        feature: The library feature ("velocity").
        component: The state whose rate of change it enters ("velocity": d velocity/dt).
        coefficient: Its fitted coefficient: the centre of its distribution where it varies between trajectories.
        interval: The coefficient's 95 % interval (low, high), or None (report.md says why).
        distribution: None for a constant coefficient, else its family and parameters ({"kind": "uniform", ...}).
        parameters: A parametric form's own parameters (``rational(velocity;v0=0.8)``: v0), each ``{"name", "value",
            "interval", "range"}``; empty for a library term.
    """

    name: str
    feature: str
    component: str
    coefficient: float
    interval: tuple[float, float] | None
    distribution: dict[str, Any] | None
    parameters: tuple[dict[str, Any], ...] = ()

    @classmethod
    def from_report(cls, term: dict[str, Any]) -> NamedTerm:
        interval = None if term["interval"] is None else (float(term["interval"][0]), float(term["interval"][1]))
        parameters = tuple(term.get("parameters") or ())
        return cls(
            term["name"],
            term["feature"],
            term["component"],
            float(term["coefficient"]),
            interval,
            term["distribution"],
            parameters,
        )


@dataclass(frozen=True)
class DiscoveryResult:
    """What :func:`otgb.discovery.pipeline.discover` found, with what its files need.

    Args:
        discovery: The workflow's record of every step (:class:`otgb.discovery.record.Discovery`).
        physics: f_p, the model discovery started from.
        facts: What the report says of the run besides the result (the measurements, the config files, ...).
        samples: The gap table's draws by source, for the distribution figure.
        components: The grey-box's component analysis, or None where no grey-box was trained.
        config: The run's resolved config as YAML data, the base of ``augmented.yaml``.
        measured: Every measured trajectory (all parts), for a next round that needs them in a file.
        source: Where they came from (:mod:`otgb.data.sources`).
        stages: Where the run's time went (:meth:`otgb.discovery.stages.Stopwatch.record`), or None (not timed).
    """

    discovery: Discovery
    physics: PhysicsModel
    facts: dict[str, Any]
    samples: dict[str, Tensor]
    components: dict | None
    config: dict[str, Any]
    measured: Tensor
    source: MeasurementSource
    stages: dict | None = None

    @cached_property
    def report(self) -> dict[str, Any]:
        """``report.json`` as a dict."""
        report = report_dict(self.discovery, self.physics, self.facts)
        report["components"] = None if self.components is None else to_json(self.components)["summary"]
        return report

    def to_dict(self) -> dict[str, Any]:
        """What ``report.json`` holds (a copy)."""
        return copy.deepcopy(self.report)

    @property
    def verdict(self) -> str:
        return self.report["verdict"]

    @property
    def outcome(self) -> str:
        """Which verdict: "gap closed", "found, not exactly", "named, not confirmed", "partly found", "nothing found"
        or "nothing detected"."""
        return self.report["outcome"]

    @property
    def confirmed(self) -> bool:
        return self.report["confirmed"]

    @property
    def found(self) -> bool:
        return self.discovery.found

    @property
    def terms(self) -> list[NamedTerm]:
        return [NamedTerm.from_report(term) for term in self.report["terms"]]

    @property
    def recalibrated(self) -> list[dict]:
        """f_p's refitted priors (report.json's ``recalibrated``): per parameter its name, the config's prior and the
        fitted one, with 95 % intervals; empty where the answer is not a recalibration."""
        return self.report["recalibrated"]

    @property
    def augmented_physics(self) -> Augmented | None:
        """The answer's model (f_p with the named terms added, its priors recalibrated where that is the answer), or
        None where it changes nothing."""
        return self.discovery.model(self.physics) if self.discovery.explained else None

    @property
    def gap(self) -> dict[str, dict[str, float]]:
        """MMD, C2ST and energy distance of each model's draws against the test part, and the Reference's."""
        return self.report["gap"]

    def print(self, file: TextIO | None = None) -> None:
        """The verdict, the named terms and the gap table, as a terminal shows them."""
        print(terminal_table(self), file=file or sys.stdout)

    def write(self, run_dir: str | Path) -> Path:
        """Write ``report.md``, ``report.json``, ``figures/`` (and ``components.json``, and ``stages.json`` where the
        run was timed) into ``run_dir``, and
        ``augmented.yaml`` where terms were named (with ``measured.npz``, the measurements, where no file of them is
        left: an array given to :meth:`MissingEffect.fit` without a run directory). Returns ``run_dir``."""
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        write_report(run_dir, self.discovery, self.physics, self.facts, self.samples, self.components, self.stages)
        if self.discovery.explained:
            config = copy.deepcopy(self.config)
            # the next round reads these measurements from a file (for generated ones, not the DGP: it would add the
            # named terms twice; for an array given from Python, a copy beside the report)
            config["data"].update(measured_path=self._measured_file(run_dir), hidden_effect=[])
            write_augmented(run_dir / "augmented.yaml", augmented_config(config, self.physics, self.discovery))
        return run_dir

    def _measured_file(self, run_dir: Path) -> str:
        path = self.source.as_file(run_dir, self.measured)
        if Path(path).is_file():
            return path
        copied = run_dir / "measured.npz"
        np.savez(copied, y=self.measured.numpy())
        return str(copied.resolve())


def terminal_table(result: DiscoveryResult) -> str:
    """The verdict, each named term (name, term, coefficient, 95 % interval, constant or its distribution) and the gap
    table, in plain text."""
    answer, *details = result.report["verdict_parts"]  # as otgb discover prints them: the answer, then its evidence
    lines = [f"verdict: {answer}", *(f"  {detail}" for detail in details), ""]
    if result.terms:
        rows = [("name", "term", "coefficient", "95 % interval", "varies")]
        for t in result.terms:
            interval = "-" if t.interval is None else f"[{t.interval[0]:.4g}, {t.interval[1]:.4g}]"
            rows.append((t.name, f"{t.feature} on d{t.component}/dt", f"{t.coefficient:.4g}", interval,
                         distribution_text(t.distribution)))  # fmt: skip
        lines += [*_aligned(rows), ""]
    rows = [("gap to the test part", "MMD", "C2ST", "energy")]
    rows += [
        (label, f"{g['mmd']:.4g}", f"{g['c2st']:.3f}", f"{g['energy']:.4g}")
        for key, label in GAP_ROWS.items()
        if (g := result.gap.get(key)) is not None
    ]
    return "\n".join(lines + _aligned(rows))


def _aligned(rows: list[tuple[str, ...]]) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows]
