"""Discovery from Python, in the scikit-learn / PySINDy style: configure, ``fit``, then read the results.

    from otgb.discovery import MissingEffect

    finder = MissingEffect("configs/pendulum.yaml", "--data.simulation_budget=32000").fit("measured.npz")
    finder.verdict_, finder.terms_, finder.augmented_physics_, finder.report_

``fit`` runs exactly what ``otgb discover`` runs (:func:`otgb.discovery.cli.discover_run`): the
same config files and overrides, the same run directory with ``report.md``, ``report.json``,
``figures/`` and ``augmented.yaml``.
"""

from __future__ import annotations

from pathlib import Path

from otgb.discovery.cli import discover_run
from otgb.errors import InputError


class MissingEffect:
    """Find what a physics model lacks from a file of its measurements.

    Args:
        *config: config files (as ``otgb discover --config``; the first names f_p), then any command-line
            overrides, e.g. ``"--data.simulation_budget=32000"`` or ``"--discover.alpha=0.01"``.

    After :meth:`fit`:
        verdict_: the report's verdict sentence (one of the outcomes below, with its numbers).
        outcome_: which verdict: "gap closed", "found, not exactly", "named, not confirmed", "partly found" (the
            library terms that came closest, not the missing effect itself), "nothing found" or "nothing detected".
        found_: whether terms were named and kept (any outcome but the last two).
        confirmed_: whether the test part confirms them: the augmented physics significantly nearer to it than f_p
            alone (:mod:`otgb.discovery.closer`) and no test telling it from the measurements.
        terms_: the kept terms, :class:`otgb.physics.LibraryTerm` with their fitted coefficient priors.
        augmented_physics_: f_p with the kept terms added (an :class:`otgb.physics.Augmented`), or None.
        report_: ``report.json`` as a dict (terms with intervals, evidence, gap table, ...).
        result_: the workflow's full :class:`otgb.discovery.workflow.Discovery`.
        run_dir_: the run directory (report, figures, ``augmented.yaml``, the grey-box's logs and checkpoints).
    """

    def __init__(self, *config: str) -> None:
        files = [c for c in config if not c.startswith("-")]
        if not files:
            raise InputError("MissingEffect: give at least one config file (the first names f_p)")
        self.overrides = [c for c in config if c.startswith("-")]
        self.config_files = files

    def fit(self, measured_path: str | Path | None = None, ckpt_path: str | Path | None = None) -> MissingEffect:
        """Run the workflow on ``measured_path`` (None: the measurements the config's hidden effect generates),
        with the grey-box trained here or loaded from ``ckpt_path``. Returns self."""
        args = [arg for path in self.config_files for arg in ("--config", str(path))]
        if measured_path is not None:
            args += ["--data.hidden_effect=[]", f"--data.measured_path={measured_path}"]
        args += self.overrides + ([f"--ckpt_path={ckpt_path}"] if ckpt_path is not None else [])
        finished = discover_run(args)
        self.run_dir_, self.result_, self.report_ = finished.run_dir, finished.result, finished.report
        self.verdict_, self.found_ = self.report_["verdict"], finished.result.found
        self.confirmed_, self.outcome_ = self.report_["confirmed"], self.report_["outcome"]
        self.terms_ = finished.result.fitted.terms() if self.found_ else []
        self.augmented_physics_ = finished.result.fitted.model(finished.physics) if self.found_ else None
        return self

    def __repr__(self) -> str:
        state = f", verdict_={self.verdict_!r}" if hasattr(self, "verdict_") else ""
        return f"MissingEffect({', '.join(map(repr, [*self.config_files, *self.overrides]))}{state})"
