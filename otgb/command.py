"""The LightningCLI of the ``otgb`` command over :class:`MapTraining` and :class:`SimulationDataModule`.

Every subcommand first loads ``otgb/configs/defaults.yaml`` (trainer, loggers, checkpointing,
optimisers), then the ``--config`` files in order, then the command-line overrides. The data
module's f_p is handed to the model at instantiation, and the model's T_max sets how many
source batches each training item holds. Three callbacks are always present, each with its own
config section: :class:`otgb.callbacks.Evaluation` (``evaluation:``, e.g.
``--evaluation.reference_repeats 10``), a :class:`BestAndLastCheckpoint` (``checkpoint:``, e.g.
``--checkpoint.monitor val/mmd``) and :class:`otgb.callbacks.ComponentAnalysis` (``components:``,
e.g. ``--components.enabled false``), which writes ``components.json`` at the end of ``otgb fit``.
``--solver`` picks how every solve runs (:mod:`otgb.physics.solvers`: compiled after a warm-up by
default). Scripts and ``otgb discover`` (:mod:`otgb.discovery.cli`) build runs with :class:`OTGBCLI`.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from lightning import LightningModule, Trainer
from lightning.pytorch.callbacks import ModelCheckpoint, ProgressBar
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only
from lightning.pytorch.utilities.exceptions import MisconfigurationException, SIGTERMException

from otgb.callbacks import ComponentAnalysis, Evaluation
from otgb.callbacks.progress import SimulationProgressBar
from otgb.errors import InputError, OutputNotWritten
from otgb.physics.solvers import COMPILE_AFTER, SOLVERS, checked_solver, set_solver

DEFAULTS = Path(__file__).parent / "configs" / "defaults.yaml"
AUTO = "auto"  # logger name / checkpoint monitor chosen from the run (see OTGBCLI)


class BestAndLastCheckpoint(ModelCheckpoint):
    """A ModelCheckpoint whose ``save_last`` writes ``last.ckpt`` at every validation, at the end of
    training and on SIGTERM, to resume from; the loggers are flushed with it.

    Lightning 2.6 writes ``last.ckpt`` only at the validations that also save a best checkpoint,
    which would make it a copy of the best one rather than the latest state.
    """

    def on_exception(self, trainer: Trainer, pl_module: LightningModule, exception: BaseException) -> None:
        """On SIGTERM (Lightning stops between two steps), save that state as ``last.ckpt`` to resume from."""
        if isinstance(exception, SIGTERMException) and self.dirpath is not None and trainer.state.fn == "fit":
            path = Path(self.dirpath) / "last.ckpt"
            trainer.save_checkpoint(path, weights_only=False)  # the whole state, said explicitly (Lightning logs a default)
            rank_zero_info(f"otgb: stopped by SIGTERM after step {trainer.global_step}; resume with --ckpt_path {path}")

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Training ended between two validations (the budget or max_steps): save its final state as last.ckpt."""
        if self.save_last is True and trainer.global_step != self._last_global_step_saved and self.dirpath is not None:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    def _save_checkpoint(self, trainer: Trainer, filepath: str) -> None:
        """Save; if the write fails (a full disk), remove the partial file, which is no checkpoint, and say what is left."""
        try:
            super()._save_checkpoint(trainer, filepath)
        except OSError as error:
            Path(filepath).unlink(missing_ok=True)
            last = Path(filepath).with_name("last.ckpt")
            left = f"; {last} is complete: resume with --ckpt_path {last}" if last.exists() and str(last) != filepath else ""
            raise OutputNotWritten(f"could not write the checkpoint {filepath} ({error.strerror}), removed it{left}") from None

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """A resume writes into a new ``version_N``: keep the earlier best score as the one to beat.

        Lightning forgets it when the folder changes, so the resumed run's first validation would be
        saved as "best" however bad. Files of the earlier folder are never removed (Lightning removes
        only those inside its own ``dirpath``), and ``last_model_path`` stays the new folder's.
        """
        if state_dict.get("dirpath", self.dirpath) == self.dirpath:
            return super().load_state_dict(state_dict)
        self.best_model_path = state_dict["best_model_path"]
        self.best_model_score = state_dict["best_model_score"]
        self.best_k_models = dict(state_dict.get("best_k_models", {}))
        self.kth_best_model_path = state_dict.get("kth_best_model_path", self.kth_best_model_path)
        self.kth_value = state_dict.get("kth_value", self.kth_value)

    def on_validation_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        super().on_validation_end(trainer, pl_module)
        skip = self._should_skip_saving_checkpoint(trainer)  # also true when a best checkpoint was just saved
        if self.save_last is True and not skip and not self._should_save_on_train_epoch_end(trainer):
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        for logger in trainer.loggers:  # the log holds every row up to the checkpoint: a resume from it loses none
            logger.save()


def source_batches(t_max: int, critic_steps: int) -> int:
    """Source batches a training step uses: one per map update, one per critic update after the first (at least 1: a
    t_max or critic_steps below 1 is the model's error to name, once it is built)."""
    return max(1, t_max + critic_steps - 1)


def measured_batches(critic_steps: int) -> int:
    """Measured batches a training step uses: one per critic update (at least 1, as :func:`source_batches`)."""
    return max(1, critic_steps)


def physics_of(datamodule: Any) -> Any:
    """The data module's f_p, as the model gets it: read at the measured file's own times where they are not its grid."""
    return datamodule.physics


DESCRIPTION = "otgb: grey-box maps that complete an incomplete physics model from unpaired measurements."
OTHER_COMMANDS = (
    "Two more commands, each with its own --help: otgb discover (name the effect that f_p misses, add it, show the "
    "gap shrink) and otgb tune (an Optuna study over a config's settings)."
)


class OTGBCLI(LightningCLI):
    """LightningCLI with otgb's shared defaults, a checkpoint section and two ``auto`` settings.

    - ``trainer.logger[*].init_args.name: auto``: the ``--config`` files' stems joined by "-"
      (``lightning_logs`` without one), so runs go to ``runs/<stem>/version_N``.
    - ``checkpoint.monitor: auto``: the data module's ``selection_metric``.

    A run that stops on bad input (:class:`InputError`) removes the log directories it made,
    unless they already hold a checkpoint.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.new_log_dirs: list[Path] = []
        try:
            super().__init__(*args, **kwargs)
        except (InputError, ValueError) as error:
            found = bad_input_in(error)
            if found is None:
                raise
            for log_dir in self.new_log_dirs:
                if log_dir.is_dir() and not any(log_dir.rglob("checkpoints")):
                    shutil.rmtree(log_dir)
            raise found from None

    def setup_parser(self, add_subcommands: bool, main_kwargs: dict[str, Any], subparser_kwargs: dict[str, Any]) -> None:
        defaults = {"default_config_files": [str(DEFAULTS)]}
        if add_subcommands:
            subparser_kwargs = {name: {**defaults, **subparser_kwargs.get(name, {})} for name in self.subcommands()}
            main_kwargs = {"description": DESCRIPTION, "epilog": OTHER_COMMANDS, **main_kwargs}
        else:
            main_kwargs = {**defaults, **main_kwargs}
        super().setup_parser(add_subcommands, main_kwargs, subparser_kwargs)

    def _prepare_subcommand_parser(self, klass: type, subcommand: str, **kwargs: Any):
        """The subcommand's parser; ``test`` prints no metric table unless ``--verbose true``: its results are in the
        run's ``metrics.md``, whose summary sentence and path the command's last lines give."""
        parser = super()._prepare_subcommand_parser(klass, subcommand, **kwargs)
        if subcommand == "test":
            parser.set_defaults(verbose=False)
        return parser

    def add_arguments_to_parser(self, parser) -> None:
        parser.link_arguments(("model.t_max", "model.critic_steps"), "data.batches_per_step", compute_fn=source_batches)
        parser.link_arguments("model.critic_steps", "data.measured_batches_per_step", compute_fn=measured_batches)
        parser.link_arguments("data", "model.physics", compute_fn=physics_of, apply_on="instantiate")
        parser.add_lightning_class_args(Evaluation, "evaluation")
        parser.add_lightning_class_args(BestAndLastCheckpoint, "checkpoint")
        parser.add_lightning_class_args(ComponentAnalysis, "components")
        parser.add_argument(
            "--solver",
            type=str,
            default="auto",
            help=f"how every fixed-step solve runs: {', '.join(SOLVERS)} (otgb.physics.solvers; auto compiles a field's "
            f"solve (a small state's whole loop, a grid's Runge-Kutta step) once it has been, or a training run plans it "
            f"to be, solved {COMPILE_AFTER} times; "
            "torchdiffeq is the reference path)",
        )

    def before_instantiate_classes(self) -> None:
        config = self.config[self.subcommand] if self.subcommand else self.config
        set_solver(checked_solver(config.solver, "--solver"))
        check_precision(config.trainer.get("precision"))
        name_loggers_after_config(config.trainer.logger, config.get("config"))
        log_dirs = share_logger_version(config.trainer.logger)
        self.new_log_dirs = [_first_new(log_dir) for log_dir in log_dirs]
        if len(log_dirs) > 1:  # e.g. --trainer.logger.init_args.save_dir, which moves only the last logger of the list
            rank_zero_info(
                f"otgb: this run's loggers write to {len(log_dirs)} folders ({', '.join(map(str, log_dirs))}); its "
                "checkpoints and figures go with the first. To move the whole run, give --trainer.logger a list with "
                "every logger's save_dir (docs/runs.md)"
            )

    def before_fit(self) -> None:
        """One line when ``--trainer.max_steps`` ends the run before its first validation: no validation metrics, no
        best checkpoint and no trajectory figures then (a shortened run is easy to ask for and was silent about it)."""
        refuse_written_log_dirs(self.trainer)
        steps, first = check_validation_in_budget(self.datamodule, self.trainer)
        stop = self.trainer.max_steps
        if 0 < stop < min(first, steps):
            rank_zero_info(
                f"otgb: --trainer.max_steps={stop} ends the run before its first validation (at step {first} of the "
                f"budget's {steps}): no validation, no best checkpoint; lower --trainer.val_check_interval or the budget"
            )

    def before_validate(self) -> None:
        refuse_written_log_dirs(self.trainer)

    def before_test(self) -> None:
        refuse_written_log_dirs(self.trainer)

    def before_predict(self) -> None:
        refuse_written_log_dirs(self.trainer)

    def instantiate_trainer(self, **kwargs: Any) -> Trainer:
        """The trainer, with :class:`SimulationProgressBar` unless the progress bar is off or the config names one."""
        config = self._get(self.config_init, "trainer", default={})
        callbacks = config.get("callbacks") or []
        if config.get("enable_progress_bar") is not False and not any(isinstance(c, ProgressBar) for c in callbacks):
            self.trainer_defaults = {**self.trainer_defaults, "callbacks": [SimulationProgressBar()]}
        try:
            return super().instantiate_trainer(**kwargs)
        except MisconfigurationException as error:  # a trainer setting Lightning rejects (an accelerator, devices, ...)
            raise InputError(f"trainer: {error}") from None
        except ValueError as error:
            raise InputError(f"trainer: {str(error).splitlines()[0]}") from None

    def instantiate_classes(self) -> None:
        super().instantiate_classes()
        config = self.config[self.subcommand] if self.subcommand else self.config
        checkpoint = self._get(self.config_init, "checkpoint")
        if checkpoint.monitor == AUTO:
            checkpoint.monitor = config.checkpoint.monitor = self.datamodule.selection_metric


FLOAT32 = (None, 32, "32", "32-true")


def check_precision(precision: object) -> None:
    """Refuse a trainer precision other than float32: Lightning's would autocast the solves and round the trajectories."""
    if precision not in FLOAT32:
        raise InputError(
            f"--trainer.precision={precision}: otgb trains in float32 (expected 32-true): a lower precision would round "
            "the solves' trajectories; a convolutional critic can convolve in bfloat16 alone "
            "(--model.critic.init_args.precision bf16-mixed)"
        )


def check_validation_in_budget(data: Any, trainer: Trainer) -> tuple[int, int]:
    """The run's training steps and its first validation step; bad input when the budget ends before that validation
    (Lightning would stop the fit with a traceback once it has started)."""
    per_step = data.batch_size * data.batches_per_step
    steps = data.simulation_budget // trainer.world_size // per_step
    every = trainer.val_check_interval
    first = every if isinstance(every, int) else max(int(steps * every), 1)  # a float: a fraction of the run
    if isinstance(every, int) and every > steps:
        raise InputError(
            f"trainer.val_check_interval={every}: data.simulation_budget={data.simulation_budget} gives only {steps} "
            f"training steps ({per_step} simulations a step on each of {trainer.world_size} process(es)); expected a "
            f"budget of at least {every * per_step * trainer.world_size} or --trainer.val_check_interval <= {steps}"
        )
    return steps, first


def name_loggers_after_config(loggers: object, config_files: list | None) -> None:
    """Replace logger name ``auto`` by the config files' stems joined by "-" (``lightning_logs`` without one).

    ``--config configs/pendulum.yaml --config configs/baselines/wgan.yaml`` logs to ``runs/pendulum-wgan``.
    """
    name = "-".join(Path(str(c)).stem for c in config_files) if config_files else "lightning_logs"
    for logger in loggers if isinstance(loggers, list) else [loggers]:
        args = getattr(logger, "init_args", None)
        if args is not None and getattr(args, "name", None) == AUTO:
            args.name = name


def logger_override(save_dir: str, name: str) -> str:
    """A ``--trainer.logger`` argument for TensorBoard + CSV logs in ``<save_dir>/<name>/version_N``."""
    loggers = [
        f"{{class_path: lightning.pytorch.loggers.{cls}, init_args: {{save_dir: {save_dir}, name: {name}}}}}"
        for cls in ("CSVLogger", "TensorBoardLogger")  # CSV first: it wants an empty folder
    ]
    return f"--trainer.logger=[{', '.join(loggers)}]"


def bad_input_in(error: BaseException) -> InputError | None:
    """The :class:`InputError` that ``error`` is or was raised from: jsonargparse wraps one raised while it builds a
    component (``--model.objective.gamma=-1``) in a ValueError about union subtypes."""
    while error is not None and not isinstance(error, InputError):
        error = error.__cause__ or error.__context__
    return error


def _first_new(path: Path) -> Path:
    """The outermost folder of ``path`` that does not exist yet (``path`` itself when its parent exists)."""
    while not path.parent.exists():
        path = path.parent
    return path


def refuse_written_log_dirs(trainer: Trainer) -> None:
    """Bad input when a logger's folder already holds a run (its ``version`` given, not chosen anew): Lightning would
    write over its logs, or stop with a traceback on its ``config.yaml``. A run's saved ``config.yaml`` pins its
    version, so running it again lands here; loading it (:func:`otgb.runs.load_run`) writes nothing and may."""
    if rank_zero_only.rank != 0:  # the other ranks start after rank 0 has made the folder
        return
    for logger in trainer.loggers:
        folder = Path(logger.log_dir) if getattr(logger, "log_dir", None) else None
        if folder is not None and folder.is_dir() and any(folder.iterdir()):
            raise InputError(
                f"trainer.logger version {logger.version!r}: {folder} already holds a run; expected a version not "
                "taken, or none (remove `version` from the config's loggers: the run, resumed or not, gets a new "
                "version_N)"
            )


def share_logger_version(loggers: object) -> list[Path]:
    """Give every configured logger that writes to the same <save_dir>/<name> one version.

    TensorBoard and CSV loggers each pick the next free ``version_N`` on their own, so the
    second one to start lands in a different folder; this picks N once for all of them.
    Returns the ``<save_dir>/<name>/version_N`` directories chosen (none of them exists yet).
    """
    if not isinstance(loggers, list):
        return []
    groups: dict[Path, list] = {}
    for logger in loggers:
        args = getattr(logger, "init_args", None)
        if args is None or getattr(args, "version", None) is not None or getattr(args, "save_dir", None) is None:
            continue
        groups.setdefault(Path(args.save_dir) / (getattr(args, "name", None) or "lightning_logs"), []).append(args)
    chosen: dict[Path, int] = {}
    for root, members in groups.items():
        taken = (
            [int(p.name.split("_")[1]) for p in root.glob("version_*") if p.name.split("_")[1].isdigit()] if root.is_dir() else []
        )
        version = chosen[root] = max(taken, default=-1) + 1
        for args in members:
            args.version = version
    return [root / f"version_{version}" for root, version in chosen.items()]
