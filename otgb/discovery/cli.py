"""``otgb discover``: find where f_p and your measurements disagree, name the missing terms, add them, check.

    otgb discover --config my_model.yaml --data.measured_path measurements.npz [--ckpt_path grey-box.ckpt]

Time against precision: ``--data.simulation_budget`` (the grey-box's training: too small and
the report says it is undertrained), ``--discover.fit_steps`` and ``--discover.fit_batch`` (each
coefficient fit), ``--discover.n_permutations`` (the disagreement maps' p-values),
``--discover.families`` (fewer prior families, fewer fits), ``--ckpt_path`` (skip training).

It takes the options of ``otgb fit`` (the same config files work; with a config's hidden
effect and no file, the measurements are generated from that DGP, which the workflow does not
see, and the report adds pointwise errors against it), a ``discover:`` section
(:class:`otgb.discovery.workflow.DiscoverySettings`) and ``--ckpt_path``, a grey-box trained on
the same measurements, to skip training. It writes ``report.md``, ``report.json``,
``figures/`` and ``augmented.yaml`` into the run directory (``runs/<config stem>/version_N``,
where the fit's logs and checkpoints also go) and prints that directory. Progress goes to stderr.
"""

from __future__ import annotations

import signal
import sys
import threading
import warnings
from argparse import RawDescriptionHelpFormatter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import yaml
from jsonargparse import DefaultHelpFormatter

from otgb.analysis.components import component_analysis
from otgb.command import OTGBCLI, check_validation_in_budget, refuse_written_log_dirs
from otgb.data import SimulationDataModule
from otgb.discovery.fit_cache import FitCache
from otgb.discovery.known import pointwise_errors
from otgb.discovery.locate import describe
from otgb.discovery.log import DivergenceLog, progress, show_on_stderr
from otgb.discovery.paired import paired_check
from otgb.discovery.report import augmented_config, write_augmented, write_report
from otgb.discovery.workflow import (
    Discovery,
    DiscoverySettings,
    Measurements,
    gap_step,
    locate_step,
    run,
    simulate_from_priors,
)
from otgb.errors import InputError
from otgb.parser_errors import ConciseParser
from otgb.physics.base import PhysicsModel
from otgb.quiet import quiet_known_harmless
from otgb.runs import load_weights
from otgb.training import MapTraining


class DescribedHelp(RawDescriptionHelpFormatter, DefaultHelpFormatter):
    """jsonargparse's help with the description's line breaks kept (its example and its list of options)."""


class DiscoverCLI(OTGBCLI):
    """The ``otgb fit`` parser plus the ``discover:`` section and ``--ckpt_path``."""

    def add_core_arguments_to_parser(self, parser) -> None:
        parser.add_class_arguments(DiscoverySettings, "discover")  # first: ``--help`` shows it before Lightning's sections
        super().add_core_arguments_to_parser(parser)

    def add_arguments_to_parser(self, parser) -> None:
        super().add_arguments_to_parser(parser)
        # The grey-box it trains is a step of the workflow, described by the report: no layer table in the terminal.
        parser.set_defaults({"trainer.enable_model_summary": False})
        parser.add_argument(
            "--ckpt_path",
            type=str | None,
            default=None,
            help="A checkpoint of an OT grey-box trained on these measurements with this config: skip training.",
        )


@dataclass
class Finished:
    """A finished ``otgb discover`` run: where it wrote, what it found, and the f_p it started from."""

    run_dir: Path
    result: Discovery
    physics: PhysicsModel
    report: dict


class Stopped(KeyboardInterrupt):
    """``otgb discover`` stopped by a signal while it named and fitted terms; the message says how to resume. A
    KeyboardInterrupt: no ``except Exception`` on the way swallows it, and a notebook treats it as an interrupt."""

    def __init__(self, signum: int, cache: FitCache | None, trained: str | None) -> None:
        self.signum, name = signum, signal.Signals(signum).name
        if cache is None or not cache.writable:
            super().__init__(f"otgb discover: stopped by {name}; no fit was kept (--discover.fit_cache: a writable folder)")
            return
        n = cache.finished()
        skip = f" (add --ckpt_path {trained} to skip training the grey-box again)" if trained else ""
        resume = f"this run's {n} finished fits and intervals are in {cache.folder}: the same command resumes{skip}"
        super().__init__(f"otgb discover: stopped by {name}; {resume}")


@contextmanager
def stopped_by_signals(cache: FitCache | None, trained: str | None) -> Iterator[None]:
    """Within it, SIGTERM (a scheduler ending the job) and Ctrl-C end the run with :class:`Stopped`; the fits finished
    so far are on disk (:mod:`otgb.discovery.fit_cache`), none half-written. ``trained``: the checkpoint of a grey-box
    this run trained."""

    def stop(signum: int, frame: object) -> None:
        raise Stopped(signum, cache, trained)

    if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
        yield
        return
    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    except Stopped:
        raise
    except KeyboardInterrupt:
        raise Stopped(signal.SIGINT, cache, trained) from None
    finally:  # None: a handler installed outside Python, which cannot be put back; the default then
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def discover(args: list[str]) -> Path:
    """Run ``otgb discover`` with its command-line arguments: the workflow, then the verdict and the run directory on
    stdout. Returns the run directory."""
    try:
        finished = discover_run(args)
    except Stopped as stopped:
        print(stopped, file=sys.stderr)
        raise SystemExit(128 + stopped.signum) from None
    answer, *details = finished.report["verdict_parts"]
    print(f"otgb discover: {answer}")
    for detail in details:
        print(f"  {detail}")
    print(f"otgb discover: report in {finished.run_dir}")
    return finished.run_dir


def refuse_position_terms_without_a_grid(settings: DiscoverySettings, physics: PhysicsModel) -> None:
    """``discover.position_degree`` asks for terms fixed in space: only a field with a free coordinate name has them."""
    if settings.position_degree and not getattr(physics, "coordinate_names", ()):
        raise InputError(
            f"discover.position_degree={settings.position_degree}: {type(physics).__name__} has no grid coordinate to "
            "offer; terms fixed in space need a field (otgb.physics.FieldModel) whose s, x or y is not a state or "
            "parameter name: expected 0"
        )


def discover_run(args: list[str]) -> Finished:
    """The workflow with ``otgb discover`` arguments: report, figures and ``augmented.yaml`` written."""
    quiet_known_harmless()  # as the otgb command, when MissingEffect calls it from Python
    with warnings.catch_warnings():  # the arguments come from the command line, after the word "discover"
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
        parser = {"prog": "otgb discover", "description": _description(), "formatter_class": DescribedHelp}
        cli = DiscoverCLI(
            MapTraining, SimulationDataModule, args=args, run=False, parser_kwargs=parser, parser_class=ConciseParser
        )
    settings: DiscoverySettings = cli.config_init["discover"]
    refuse_position_terms_without_a_grid(settings, cli.datamodule.physics)
    refuse_written_log_dirs(cli.trainer)  # the report goes into the trainer's log folder
    settings.cache_beside(Path(cli.trainer.log_dir).parent)
    device = cli.trainer.strategy.root_device  # the coefficient fits run where the grey-box trains, on a CUDA device
    settings.device = device if device.type == "cuda" else torch.device("cpu")  # (Apple's MPS has no float64 for scores)
    if cli.config.get("ckpt_path") is None:
        check_validation_in_budget(cli.datamodule, cli.trainer)
    show_on_stderr()
    datamodule, module, trainer = cli.datamodule, cli.model, cli.trainer
    data = Measurements.from_datamodule(datamodule)
    physics = datamodule.physics

    def as_measured():  # simulations compared with the measurements carry their noise; the truth does not
        return physics.measured_with_noise(datamodule.measurement_noise, settings.seed + 7919)

    paired = None  # f_p on the training part's recorded inputs, against the noise the user states
    if data.pairable():
        paired = paired_check(physics, data.train, *data.train_inputs, data.noise)
    with as_measured():
        before = locate_step(physics, data.train, settings, paired=paired)
    progress(describe(before))
    run_dir = Path(trainer.log_dir)
    components = None
    if before.any_significant:
        given = cli.config.get("ckpt_path")
        loaded = load_or_fit(cli, given)
        components = component_analysis(module, datamodule, seed=settings.seed)
        with as_measured(), stopped_by_signals(settings.cache, loaded if given is None else None):
            result = run(module, data, settings, before)
        process = datamodule.source.pointwise_process
        if process is not None:
            augmented = result.fitted.model(physics) if result.found else None
            with DivergenceLog() as log:
                result.pointwise = pointwise_errors(module, process, augmented, datamodule.test_set, settings.seed)
            result.diverged += log.records
    else:
        result = Discovery(before, describe(before))
        with as_measured():
            result.draws = {"f_p": simulate_from_priors(physics, len(data.test), settings.seed, "gap-f_p")}
        result.gap = gap_step(result.draws, data.test, settings)
    samples = {"measured": data.test, **{k: v for k, v in result.draws.items() if k != "greybox"}}
    facts = {"description": datamodule.describe(), "config": [str(c) for c in cli.config.get("config") or []]}
    facts["measurement_noise"] = datamodule.measurement_noise
    if datamodule.trained_on:  # the grey-box's checkpoint came from other measurements (said at load, kept here)
        facts["grey_box_trained_on"] = datamodule.trained_on
    if settings.cache is not None:
        facts["fit_cache"] = settings.cache.summary()
    run_dir.mkdir(parents=True, exist_ok=True)
    report = write_report(run_dir, result, physics, facts, samples, components)
    if result.found:
        config = yaml.safe_load(cli.parser.dump(cli.config, format="yaml", skip_none=False))
        # the next round reads these measurements from a file (for generated ones, not the DGP: it would add the named
        # terms twice)
        measured = datamodule.source.as_file(run_dir, torch.cat([data.train, data.val, data.test]))
        config["data"].update(measured_path=measured, hidden_effect=[])
        write_augmented(run_dir / "augmented.yaml", augmented_config(config, physics, result))
    return Finished(run_dir, result, physics, report)


def _description() -> str:
    """What ``otgb discover`` does, an example, and which options trade time for precision (``--help``'s opening)."""
    opening, example, trade, _ = __doc__.split("\n\n", 3)
    return "\n\n".join([opening.replace("``", ""), example, trade.replace("``", "")])


def load_or_fit(cli: Any, ckpt_path: str | None) -> str | None:
    """Load the grey-box's weights from ``ckpt_path``, or train it and load its best checkpoint; returns the checkpoint
    loaded."""
    if ckpt_path is None:
        progress("learning: training the OT grey-box on the measured training part")
        cli.trainer.fit(cli.model, cli.datamodule)
        ckpt_path = getattr(cli.trainer.checkpoint_callback, "best_model_path", "") or None
        if ckpt_path is None:
            return None
    load_weights(cli.model, ckpt_path, cli.datamodule)
    return ckpt_path
