"""The ``otgb`` command.

    otgb fit --config configs/pendulum.yaml [--model.objective.gamma 0.5 --trainer.max_steps 2000 ...]
    otgb validate|test --config configs/pendulum.yaml --ckpt_path runs/.../last.ckpt
    otgb discover --config my_model.yaml --data.measured_path measurements.npz   (otgb.discovery)

``fit`` / ``validate`` / ``test`` run :class:`otgb.command.OTGBCLI`; ``discover`` runs
:func:`otgb.discovery.cli.discover`. ``otgb test`` writes ``metrics.json`` and ``metrics.md`` into its
run directory and prints the report's summary sentence (Lightning's metric table with ``--verbose
true``); each command ends with a line naming its run directory. Bad user input
(:class:`otgb.errors.InputError`, or the parser's own errors) ends the command with one line
``otgb: error: <message>`` and exit status 2; a diverged training or f_p solve ends it with one such
line and status 1.
"""

from __future__ import annotations

import errno
import logging
import signal
import sys
from pathlib import Path

from lightning.fabric.utilities.rank_zero import rank_zero_only
from lightning.pytorch.utilities.exceptions import SIGTERMException

from otgb.command import OTGBCLI
from otgb.data import SimulationDataModule
from otgb.errors import InputError, OutputNotWritten
from otgb.guard import TrainingDiverged
from otgb.parser_errors import ConciseParser
from otgb.physics.base import SimulationDiverged
from otgb.quiet import quiet_known_harmless
from otgb.reports import summary_of
from otgb.training import MapTraining

MAIN_FILES = ("metrics.md", "metrics.json", "config.yaml", "metrics.csv", "checkpoints", "figures", "components.json")


def closing_line(subcommand: str, run: Path) -> str:
    """The last line of ``otgb fit`` / ``otgb test``: the run directory and the main files in it."""
    present = [f"{name}/" if (run / name).is_dir() else name for name in MAIN_FILES if (run / name).exists()]
    return f"otgb {subcommand}: results in {run}: {', '.join(present) or 'nothing written'}"


def show_notices() -> None:
    """otgb's notices while a run works (INFO of the ``otgb.solvers`` logger: a solve being compiled) and its warnings
    on stderr, one line each, from the first process only (idempotent)."""
    logger = logging.getLogger("otgb.solvers")
    if any(getattr(handler, "otgb_notices", False) for handler in logger.handlers):
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(lambda _: getattr(rank_zero_only, "rank", 0) == 0)
    handler.otgb_notices = True
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)


def main(args: list[str] | None = None) -> None:
    """Run the ``otgb`` command; bad user input ends it with one line on stderr and status 2."""
    logging.getLogger("lightning.fabric.utilities.seed").setLevel(logging.WARNING)  # the seed is in config.yaml
    quiet_known_harmless()
    show_notices()
    argv = sys.argv[1:] if args is None else args
    try:
        if argv[:1] == ["tune"]:
            from otgb.tune import tune

            tune(argv[1:])
            return
        if argv[:1] == ["discover"]:
            from otgb.discovery.cli import discover

            discover(argv[1:])
            return
        cli = OTGBCLI(MapTraining, SimulationDataModule, args=args, parser_class=ConciseParser)
        loggers = cli.trainer.loggers  # not trainer.log_dir: a collective under DDP, and the other ranks have finished
        if cli.trainer.is_global_zero and loggers and loggers[0].log_dir:
            run = Path(loggers[0].log_dir)
            if cli.subcommand == "test" and (sentence := summary_of(run)):  # results on stdout, as discover and tune
                print(f"otgb test: {sentence}")
            print(closing_line(cli.subcommand, run))
    except InputError as error:
        print(f"otgb: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    except (TrainingDiverged, SimulationDiverged, OutputNotWritten) as error:
        print(f"otgb: error: {error}", file=sys.stderr)
        raise SystemExit(1) from None
    except OSError as error:  # a log or report that could not be written (a full disk, no permission)
        if error.errno not in (errno.ENOSPC, errno.EACCES, errno.EDQUOT):
            raise
        print(f"otgb: error: could not write {error.filename}: {error.strerror}", file=sys.stderr)
        raise SystemExit(1) from None
    except SIGTERMException:  # the checkpoint callback said where the state is
        raise SystemExit(128 + signal.SIGTERM) from None


if __name__ == "__main__":
    main()
