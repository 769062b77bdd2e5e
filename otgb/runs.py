"""Runs from Python: load one (config files and a checkpoint to the model and the data module, built as ``otgb``
builds them, without training, printing or writing anything), or fit and test one as separate ``otgb`` processes.

    from otgb.runs import fit_and_test, load_run

    run = load_run("configs/pendulum.yaml", "--data.n_measured=500", ckpt_path="runs/pendulum/version_0/checkpoints/last.ckpt")
    run.model, run.datamodule, run.trainer
    run = load_run("runs/pendulum/version_0/config.yaml", ckpt_path="runs/pendulum/version_0/checkpoints/best-step=900.ckpt")

    report = fit_and_test(Path("runs/seed0"), ["--config", "configs/pendulum.yaml", "--seed_everything=0"])
    report["model"]["abs_err"]["mean"], report["fit_s"]
"""

from __future__ import annotations

import json
import logging
import platform
import subprocess
import sys
import time
import warnings
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from lightning import Trainer

from otgb.command import OTGBCLI, logger_override
from otgb.data import SimulationDataModule
from otgb.errors import InputError
from otgb.metrics.classifiers import native_bf16
from otgb.parser_errors import ConciseParser
from otgb.quiet import quiet_known_harmless
from otgb.training import MapTraining


class RunLoader(OTGBCLI):
    """The ``otgb`` parser without subcommands that also takes a run's saved ``config.yaml``, which holds its
    command's ``ckpt_path`` and ``weights_only`` (and a test's or validation's ``verbose``): read and dropped
    (:func:`load_run`'s ``ckpt_path`` decides), so that the config a loaded run saves is one ``otgb fit`` takes
    as it is (a tuning trial's, say). Its loggers write to a new ``version_N`` (:func:`release_taken_versions`)."""

    COMMAND_ONLY = ("ckpt_path", "weights_only", "verbose")

    def add_arguments_to_parser(self, parser) -> None:
        super().add_arguments_to_parser(parser)
        parser.add_argument("--ckpt_path", type=str | None, default=None, help="unused here: load_run's ckpt_path decides")
        parser.add_argument("--weights_only", type=bool | None, default=None, help="unused here")
        parser.add_argument("--verbose", type=bool | None, default=None, help="unused here")

    def before_instantiate_classes(self) -> None:
        release_taken_versions(self.config.trainer.logger)
        super().before_instantiate_classes()
        for key in self.COMMAND_ONLY:
            del self.config[key]


def release_taken_versions(loggers: object) -> None:
    """Unpin each logger version whose folder already holds a run (a saved config.yaml pins its own): the loaded
    run's trainer then writes to the next free ``version_N``, never into the run it was loaded from."""
    for logger in loggers if isinstance(loggers, list) else []:
        args = getattr(logger, "init_args", None)
        version = getattr(args, "version", None)
        if version is None or getattr(args, "save_dir", None) is None:
            continue
        folder = Path(args.save_dir) / (getattr(args, "name", None) or "lightning_logs")
        folder /= f"version_{version}" if isinstance(version, int) else str(version)
        if folder.is_dir() and any(folder.iterdir()):
            args.version = None


@dataclass
class Run:
    """A run's objects: the LightningModule (weights from the checkpoint, if one was given), the data module, the
    trainer (not started) and the composed config."""

    model: MapTraining
    datamodule: SimulationDataModule
    trainer: Trainer
    config: Any


def load_run(config: str | Path | Sequence[str | Path], *overrides: str, ckpt_path: str | Path | None = None) -> Run:
    """Build a run from ``config`` (one config file, or several composed in order) and command-line ``overrides``
    (``"--trainer.max_steps=5"``, or ``"--trainer.max_steps", "5"``); with ``ckpt_path``, the checkpoint's weights are
    loaded into the model."""
    files = [config] if isinstance(config, (str, Path)) else list(config)
    args = [arg for path in files for arg in ("--config", str(path))] + list(overrides)
    quiet_known_harmless()  # as the otgb command: a script's run is trained, tested and logged alike
    with _quiet():
        cli = RunLoader(MapTraining, SimulationDataModule, run=False, args=args, parser_class=ConciseParser)
    if ckpt_path is not None:
        load_weights(cli.model, ckpt_path, cli.datamodule)
    return Run(cli.model, cli.datamodule, cli.trainer, cli.config)


def load_weights(model: MapTraining, ckpt_path: str | Path, datamodule: SimulationDataModule | None = None) -> None:
    """The checkpoint's weights into ``model``; a missing file or another model's checkpoint is an :class:`InputError`.
    With ``datamodule``, a checkpoint trained on other measurements than its own costs a warning
    (:meth:`~otgb.data.SimulationDataModule.compare_with_training`)."""
    path = Path(ckpt_path)
    if not path.is_file():
        raise InputError(f"ckpt_path={str(ckpt_path)!r}: no such checkpoint file")
    state = torch.load(path, map_location="cpu", weights_only=False)
    try:
        model.load_state_dict(state["state_dict"])
    except (KeyError, RuntimeError) as error:
        first = str(error).splitlines()[0]
        raise InputError(f"ckpt_path={str(ckpt_path)!r}: not a checkpoint of this config's model ({first})") from None
    model.restored_step, model.loaded_from = state.get("global_step"), str(path)
    if datamodule is not None:
        datamodule.compare_with_training(state.get(type(datamodule).__qualname__, {}))


@contextmanager
def _quiet():
    """No start-up lines: Lightning's note that ``args`` is meant for Python use (it is, here), the seed line, and the
    data module's evaluation-mode line (nothing is evaluated)."""
    loggers = [logging.getLogger(name) for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.seed")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.WARNING)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


def newest(folder: Path, pattern: str) -> Path | None:
    """The most recently written file under ``folder`` matching the glob ``pattern`` (a resumed run writes the next
    ``version_N``), or None."""
    found = sorted(Path(folder).glob(pattern), key=lambda p: p.stat().st_mtime)
    return found[-1] if found else None


def asks_for_gpu(overrides: list[str]) -> bool:
    """Whether otgb command-line ``overrides`` choose a GPU: ``--trainer.accelerator=gpu`` or ``--trainer.accelerator gpu``
    (or ``cuda``)."""
    values = []
    for arg, after in zip(overrides, [*overrides[1:], ""]):
        key, equals, value = arg.partition("=")
        if key == "--trainer.accelerator":
            values.append(value if equals else after)
    return any(value.strip() in ("gpu", "cuda") for value in values)


def machine(gpu: bool = False) -> str:
    """The machine a benchmark ran on, for its result files: the GPU's name when ``gpu``, else the CPU (its model, and
    whether it multiplies bfloat16 natively: the judges' arithmetic depends on it) and its threads."""
    if gpu and torch.cuda.is_available():
        return f"{torch.cuda.get_device_name()}, torch {torch.__version__}"
    cpu = " ".join(filter(None, [platform.processor() or platform.machine(), cpu_model()]))
    cpu += ", native bf16" if native_bf16(torch.device("cpu")) else ""
    return f"{cpu}, {torch.get_num_threads()} threads, torch {torch.__version__}"


def cpu_model() -> str:
    """The CPU's model name where the system tells it (Linux's /proc/cpuinfo), else ""."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return ""
    return next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), "")


@dataclass(frozen=True)
class Finished:
    """How an ``otgb`` process ended: its exit status and its wall time in seconds."""

    returncode: int
    seconds: float


def launch_otgb(args: Sequence[str], log: Path, cwd: Path | None = None) -> Finished:
    """``otgb <args>`` as a separate process (in ``cwd``), its output appended to ``log``; how it ended, failed or not
    (a benchmark that goes on to its next case records a failure)."""
    started = time.perf_counter()
    Path(log).parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as handle:
        done = subprocess.run([sys.executable, "-m", "otgb.cli", *args], cwd=cwd, stdout=handle, stderr=subprocess.STDOUT)
    return Finished(done.returncode, time.perf_counter() - started)


def run_otgb(args: Sequence[str], log: Path, cwd: Path | None = None) -> float:
    """:func:`launch_otgb`'s wall time in seconds; a failure exits the calling script with one line naming the command
    and the log."""
    finished = launch_otgb(args, log, cwd)
    if finished.returncode != 0:
        raise SystemExit(f"otgb {args[0]} failed (exit {finished.returncode}); its output: {log}")
    return finished.seconds


def fit_and_test(folder: Path, args: Sequence[str], checkpoint: str = "best") -> dict:
    """``otgb fit <args>`` then ``otgb test <args>`` on its ``best`` (or ``last``) checkpoint, logged under ``folder``
    (``fit/`` and ``test/``, output without progress bars in ``otgb.log``); the test's metrics.json with the fit's
    seconds as ``fit_s`` and whether it resumed as ``resumed``.

    Resumable: a folder with a test report is returned as it is, and an interrupted fit continues from its
    ``last.ckpt`` (the resumed fit writes the next ``version_N``, and ``fit_s`` is the resumed part's time)."""
    folder = Path(folder)
    timing = folder / "fit_seconds.json"
    report = newest(folder / "test", "version_*/metrics.json")
    if report is not None:
        return {**json.loads(report.read_text()), **json.loads(timing.read_text())}
    log, args = folder / "otgb.log", [*args, "--trainer.enable_progress_bar=false"]
    last = newest(folder / "fit", "version_*/checkpoints/last.ckpt")
    resume = [f"--ckpt_path={last}"] if last is not None else []
    seconds = run_otgb(["fit", *args, logger_override(str(folder), "fit"), *resume], log)
    timing.write_text(json.dumps({"fit_s": seconds, "resumed": bool(resume)}))
    chosen = newest(folder / "fit", f"version_*/checkpoints/{checkpoint}*.ckpt")
    run_otgb(["test", *args, logger_override(str(folder), "test"), f"--ckpt_path={chosen}"], log)
    return {**json.loads(newest(folder / "test", "version_*/metrics.json").read_text()), **json.loads(timing.read_text())}
