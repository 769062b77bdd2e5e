"""What a discovery run is built from: the config parsed once into Lightning's objects and frozen settings, and the
signals that stop it with its finished fits kept."""

from __future__ import annotations

import signal
import threading
import warnings
from argparse import RawDescriptionHelpFormatter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from jsonargparse import DefaultHelpFormatter
from lightning import Trainer

from otgb.command import OTGBCLI, check_validation_in_budget, refuse_written_log_dirs
from otgb.data import SimulationDataModule
from otgb.discovery.fit_cache import FitCache
from otgb.discovery.settings import Context, DiscoverySettings
from otgb.errors import InputError
from otgb.parser_errors import ConciseParser
from otgb.physics.base import PhysicsModel
from otgb.physics.priors import Constant
from otgb.physics.terms import FormTerm
from otgb.quiet import quiet_known_harmless
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


@dataclass(frozen=True)
class Session:
    """A parsed discovery run: the Lightning objects (built, not started), its settings and context, the grey-box checkpoint to
    load (None: train one), the resolved config as YAML data (the base of ``augmented.yaml``) and the config files it
    came from."""

    datamodule: SimulationDataModule
    module: MapTraining
    trainer: Trainer
    settings: DiscoverySettings
    context: Context
    ckpt_path: str | None
    config: dict[str, Any]
    config_files: tuple[str, ...]

    @property
    def physics(self) -> PhysicsModel:
        return self.datamodule.physics

    @property
    def log_dir(self) -> Path:
        """The trainer's run directory (``runs/<config stem>/version_N`` by default), where the report goes."""
        return Path(self.trainer.log_dir)


def build(args: list[str], parser: dict[str, Any] | None = None) -> Session:
    """Parse ``otgb discover`` arguments into a :class:`Session`; bad input is an :class:`InputError` before anything
    is written. ``parser``: the argument parser's keyword arguments (its name and help; ``raise_input_errors``: a
    bad option raises its one line as an InputError instead of printing it and exiting, for calls from Python)."""
    quiet_known_harmless()  # as the otgb command, when discovery runs from Python
    with warnings.catch_warnings():  # the arguments come from the command line, after the word "discover"
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
        cli = DiscoverCLI(
            MapTraining, SimulationDataModule, args=args, run=False, parser_kwargs=parser or {}, parser_class=ConciseParser
        )
    settings: DiscoverySettings = cli.config_init["discover"]
    refuse_position_terms_without_a_grid(settings, cli.datamodule.physics)
    refuse_forms_that_do_not_fit(settings, cli.datamodule.physics)
    refuse_written_log_dirs(cli.trainer)  # the report goes into the trainer's log folder
    # the fits' cache beside the run directories; the fits on the grey-box's device where it is a CUDA device
    context = Context.of(settings, Path(cli.trainer.log_dir).parent, cli.trainer.strategy.root_device)
    ckpt_path = cli.config.get("ckpt_path")
    if ckpt_path is None:
        check_validation_in_budget(cli.datamodule, cli.trainer)
    config = yaml.safe_load(cli.parser.dump(cli.config, format="yaml", skip_none=False))
    files = tuple(str(c) for c in cli.config.get("config") or [])
    return Session(cli.datamodule, cli.model, cli.trainer, settings, context, ckpt_path, config, files)


def refuse_position_terms_without_a_grid(settings: DiscoverySettings, physics: PhysicsModel) -> None:
    """``discover.position_degree`` asks for terms fixed in space: only a field with a free coordinate name has them."""
    if settings.library.position_degree and not getattr(physics, "coordinate_names", ()):
        raise InputError(
            f"discover.position_degree={settings.library.position_degree}: {type(physics).__name__} has no grid coordinate to "
            "offer; terms fixed in space need a field (otgb.physics.FieldModel) whose s, x or y is not a state or "
            "parameter name: expected 0"
        )


def refuse_forms_that_do_not_fit(settings: DiscoverySettings, physics: PhysicsModel) -> None:
    """Each declared form's component and variables must be names of f_p (before any training)."""
    for i, entry in enumerate(settings.fits.forms):
        parameters = {k: Constant(1.0) for k in entry["ranges"]}
        term = FormTerm(entry["class_path"], entry["component"], entry["variables"], Constant(0.0), parameters)
        try:
            term.check_model(physics)
        except InputError as error:
            raise InputError(f"discover.forms[{i}]: {error}") from None


class Stopped(KeyboardInterrupt):
    """A discovery run stopped by a signal while it named and fitted terms; the message says how to resume. A
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
