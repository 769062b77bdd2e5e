"""``otgb tune``: a hyperparameter search on Optuna over any config key, resumable and shared by many workers.

    otgb tune --config configs/pendulum.yaml --tune.space space.yaml --tune.trials 12 [fit overrides ...]

``space.yaml`` maps config keys, as ``otgb fit`` spells them, to a range::

    model.map_optimizer.init_args.lr: {log_uniform: [1.0e-4, 3.0e-3]}
    data.batch_size: {choice: [16, 32, 64]}
    model.t_max: {int: [1, 4]}
    model.ema_decay: {uniform: [0.99, 0.999]}

The first trial runs the config's own settings (for the searched keys whose values lie in the
space), so the study's best is never worse than where it started, at the study's budget. Each
trial is a real ``otgb fit`` run (``<study dir>/trial_NNNN/version_N``: logs, checkpoints,
``config.yaml``) scored by the run's own selection metric (``checkpoint.monitor``: ``val/abs_err``
against a configured process, ``val/energy`` against a file of measurements), the best value over
its validations; trials whose validation curve is worse than the median of earlier trials at the
same step are pruned there. The study lives in an Optuna storage (default: SQLite,
``<study dir>/study.db``): run the same command again, after an interruption or in another
process or node that reaches the storage, and the workers share one study until ``--tune.trials``
trials have finished. A SIGTERM stops the running trial, which is queued again for the next run;
a trial whose worker was killed outright is queued again once its heartbeat is stale.

At the end: ``trials.md`` (every trial: state, score, settings, wall time, run directory),
``best.yaml`` (the best trial's complete config, which ``otgb fit`` takes as it is), and Optuna's
``history.png`` and ``importances.png``, all in the study directory.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import optuna
import yaml
from lightning import Callback, LightningModule, Trainer
from lightning.pytorch.utilities.exceptions import SIGTERMException

from otgb.analysis.figures import close, save
from otgb.command import logger_override
from otgb.errors import InputError
from otgb.guard import TrainingDiverged
from otgb.physics.base import SimulationDiverged
from otgb.runs import load_run

KINDS = ("uniform", "log_uniform", "int", "choice")
SAMPLERS = {"tpe": optuna.samplers.TPESampler, "random": optuna.samplers.RandomSampler}
OPEN_ATTEMPTS = 4
HEARTBEAT_S, GRACE_S = 30, 90  # a trial whose worker stopped beating for GRACE_S is queued again


@dataclass
class Settings:
    """The ``--tune.*`` options: what to search, how long, where the study lives."""

    space: Path
    trials: int
    timeout: float | None
    sampler: str
    pruner: str
    study: str | None
    storage: str | None
    seed: int


class _Parser(argparse.ArgumentParser):
    """``--tune.*`` options whose errors are one line (:class:`InputError`), as the rest of the command's."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise InputError(f"tune: {message}; list the options with: otgb tune --help")


def parse(argv: list[str]) -> tuple[Settings, list[str], list[str]]:
    """(tune settings, config files, fit overrides) from ``otgb tune``'s arguments."""
    parser = _Parser(prog="otgb tune", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-c", "--config", action="append", required=True, help="config files, as for otgb fit")
    parser.add_argument("--tune.space", dest="space", type=Path, required=True, help="YAML file: config key -> range")
    parser.add_argument("--tune.trials", dest="trials", type=int, default=12, help="trials the study runs in all")
    parser.add_argument("--tune.timeout", dest="timeout", type=float, default=None, help="seconds this worker may run")
    parser.add_argument("--tune.sampler", dest="sampler", default="tpe", choices=sorted(SAMPLERS))
    parser.add_argument("--tune.pruner", dest="pruner", default="median", choices=["median", "none"])
    parser.add_argument("--tune.study", dest="study", default=None, help="study name (default: the configs' stems)")
    parser.add_argument("--tune.storage", dest="storage", default=None, help="Optuna storage URL, or a .log journal file")
    parser.add_argument("--tune.seed", dest="seed", type=int, default=0, help="the sampler's seed")
    known, overrides = parser.parse_known_args(argv)
    settings = Settings(**{k: v for k, v in vars(known).items() if k != "config"})
    if settings.trials < 1:
        raise InputError(f"tune.trials={settings.trials}: expected >= 1")
    if settings.timeout is not None and settings.timeout <= 0:
        raise InputError(f"tune.timeout={settings.timeout}: expected a positive number of seconds")
    return settings, known.config, overrides


def read_space(path: Path, keys: list[str]) -> dict[str, dict[str, list]]:
    """The search space: config key -> {kind: range}, checked against the config's ``keys``."""
    if not path.is_file():
        raise InputError(f"tune.space={str(path)!r}: no such file")
    try:
        space = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise InputError(f"tune.space={str(path)!r}: not YAML ({str(error).splitlines()[0]})") from None
    if not isinstance(space, dict) or not space:
        raise InputError(
            f"tune.space={str(path)!r}: expected a mapping of config keys to ranges, e.g. 'data.batch_size: {{choice: [16, 32]}}'"
        )
    for key, spec in space.items():
        where = f"tune.space {path}, {key!r}"
        if key not in keys:
            near = difflib.get_close_matches(key, keys, n=2)
            hint = f" (did you mean {' or '.join(near)}?)" if near else ""
            raise InputError(f"{where}: not a setting of this config{hint}; `otgb fit --config ... --print_config` lists them")
        if not isinstance(spec, dict) or len(spec) != 1 or next(iter(spec)) not in KINDS:
            raise InputError(f"{where}: expected one of {', '.join(f'{{{k}: ...}}' for k in KINDS)}, got {spec!r}")
        _check_range(where, *next(iter(spec.items())))
    return space


def _check_range(where: str, kind: str, values: Any) -> None:
    if kind == "choice":
        if not isinstance(values, list) or not values:
            raise InputError(f"{where}: choice needs a non-empty list of values, got {values!r}")
        return
    if not (isinstance(values, list) and len(values) == 2 and all(isinstance(v, (int, float)) for v in values)):
        raise InputError(f"{where}: {kind} needs [low, high], got {values!r}")
    low, high = values
    if not low < high or (kind == "log_uniform" and low <= 0) or (kind == "int" and not all(isinstance(v, int) for v in values)):
        need = "0 < low < high" if kind == "log_uniform" else "integers low < high" if kind == "int" else "low < high"
        raise InputError(f"{where}: the range {values} is empty or invalid; expected {need}")


def in_range(value: Any, spec: dict[str, list]) -> bool:
    """Whether a config's own ``value`` lies in a key's range (a starting point the sampler may take)."""
    kind, values = next(iter(spec.items()))
    if kind == "choice":
        return value in values
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (kind == "int" and not isinstance(value, int)):
        return False
    return values[0] <= value <= values[1]


def suggest(trial: optuna.Trial, key: str, spec: dict[str, list]) -> Any:
    kind, values = next(iter(spec.items()))
    if kind == "choice":
        return trial.suggest_categorical(key, values)
    if kind == "int":
        return trial.suggest_int(key, *values)
    return trial.suggest_float(key, *values, log=kind == "log_uniform")


WARM_UP = 1 / 3  # share of a trial's steps before it may be pruned: early validation curves are noisy and cross


class Pruning(Callback):
    """Reports the selection metric to the trial after each validation and, after the first :data:`WARM_UP` of the
    run, stops a trial the pruner rejects."""

    def __init__(self, trial: optuna.Trial, monitor: str) -> None:
        self.trial, self.monitor = trial, monitor

    def on_validation_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        value = trainer.callback_metrics.get(self.monitor)
        if trainer.sanity_checking or value is None or not math.isfinite(float(value)):
            return
        self.trial.report(float(value), step=trainer.global_step)
        if trainer.global_step >= WARM_UP * trainer.estimated_stepping_batches and self.trial.should_prune():
            raise optuna.TrialPruned(f"{self.monitor} {float(value):.4g} at step {trainer.global_step}")


class Study:
    """One study: its storage, its directory, the trial objective and the results it writes."""

    def __init__(self, settings: Settings, configs: list[str], overrides: list[str]) -> None:
        self.settings, self.configs, self.overrides = settings, configs, overrides
        base = load_run(configs, *overrides)  # bad configs and overrides fail here, before anything is written
        self.monitor = base.datamodule.selection_metric if _monitor(base.config) == "auto" else _monitor(base.config)
        self.space = read_space(settings.space, list(base.config.keys()))
        own = {key: base.config.get(key) for key in self.space}
        self.baseline = {key: value for key, value in own.items() if in_range(value, self.space[key])}
        self.name = settings.study or "-".join(Path(c).stem for c in configs)
        self.directory = Path("runs") / f"tune-{self.name}"
        self.study = self._open()

    def _open(self) -> optuna.Study:
        storage = self._storage()
        sampler = SAMPLERS[self.settings.sampler](seed=self.settings.seed)
        pruner = (
            optuna.pruners.MedianPruner(n_startup_trials=3) if self.settings.pruner == "median" else optuna.pruners.NopPruner()
        )
        study = optuna.create_study(storage=storage, study_name=self.name, sampler=sampler, pruner=pruner, load_if_exists=True)
        recorded = study.user_attrs.get("space")
        if recorded is None:
            study.set_user_attr("space", self.space)
            study.set_user_attr("monitor", self.monitor)
        elif recorded != self.space:
            raise InputError(
                f"tune.study={self.name!r}: this study was started with another space ({json.dumps(recorded)}); give "
                "another --tune.study name or the same space"
            )
        return study

    def _storage(self) -> optuna.storages.BaseStorage:
        url = self.settings.storage
        if url is None:
            self.directory.mkdir(parents=True, exist_ok=True)
            url = f"sqlite:///{(self.directory / 'study.db').resolve()}"
        if url.endswith(".log"):  # a journal file: for file systems where SQLite's locks are unsafe (NFS)
            return optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(url))
        retry = optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=3)
        for attempt in range(OPEN_ATTEMPTS):  # workers started together race to create the tables of a new storage
            try:
                return optuna.storages.RDBStorage(
                    url, heartbeat_interval=HEARTBEAT_S, grace_period=GRACE_S, heartbeat_stale_trial_callback=retry
                )
            except Exception as error:  # noqa: BLE001 - SQLAlchemy's errors differ by database
                if attempt == OPEN_ATTEMPTS - 1:
                    raise InputError(f"tune.storage={url!r}: cannot be opened ({str(error).splitlines()[0]})") from None
                time.sleep(1.0 + attempt)

    def finished(self) -> int:
        """Trials that count toward ``--tune.trials``: completed, pruned, or failed for a reason of their own."""
        trials = self.study.get_trials(deepcopy=False)
        done = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)
        return sum(
            t.state in done or (t.state == optuna.trial.TrialState.FAIL and "failed_because" in t.user_attrs) for t in trials
        )

    def running(self) -> int:
        return len(self.study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)))

    def objective(self, trial: optuna.Trial) -> float:
        # Seeded by the trial's number, unique across workers and runs: a resumed or second worker draws other values
        # than the first (one seeded sampler per process would repeat its draws), and one worker's study is reproducible.
        sampler = SAMPLERS[self.settings.sampler](seed=self.settings.seed + trial.number)
        if trial.number == 0 and self.baseline:  # the config's own settings first: numbers are unique across workers
            sampler = optuna.samplers.PartialFixedSampler(self.baseline, sampler)
        self.study.sampler = sampler
        values = {key: suggest(trial, key, spec) for key, spec in self.space.items()}
        settings = [
            f"--{key}={yaml.safe_dump(value, default_flow_style=True).strip().removesuffix('...').strip()}"
            for key, value in values.items()
        ]
        started = time.time()
        try:
            run = load_run(
                self.configs, *self.overrides, *settings, logger_override(str(self.directory), f"trial_{trial.number:04d}")
            )
            run.trainer.callbacks.append(Pruning(trial, self.monitor))
            trial.set_user_attr("run_dir", str(run.trainer.log_dir))
            run.trainer.fit(run.model, run.datamodule)
        except SIGTERMException:  # a SystemExit, which Optuna leaves running: failed here, and queued for the next run
            trial.set_user_attr("wall_s", time.time() - started)
            self.study.tell(trial, state=optuna.trial.TrialState.FAIL)
            self.study.enqueue_trial(trial.params, skip_if_exists=False)
            raise
        except (InputError, TrainingDiverged, SimulationDiverged) as error:
            trial.set_user_attr("failed_because", str(error))
            score = None
        except SystemExit as error:  # the config parser rejected a sampled value (its one line is on stderr)
            if error.code != 2:
                raise
            trial.set_user_attr("failed_because", f"the config parser rejected these settings: {values}")
            score = None
        except optuna.TrialPruned:
            trial.set_user_attr("wall_s", time.time() - started)
            raise
        else:
            score = run.trainer.checkpoint_callback.best_model_score
            if score is None or not math.isfinite(float(score)):
                trial.set_user_attr("failed_because", f"no finite {self.monitor} was logged")
                score = None
        trial.set_user_attr("wall_s", time.time() - started)
        if score is None:
            return float("nan")
        return float(score)

    def optimize(self) -> None:
        """Trials one at a time until the study has ``--tune.trials`` finished or running (over all workers), or this
        worker's time is up."""
        deadline = None if self.settings.timeout is None else time.time() + self.settings.timeout
        while deadline is None or time.time() < deadline:
            optuna.storages.fail_stale_trials(self.study)  # a killed worker's trial: failed, then queued again
            if self.finished() + self.running() >= self.settings.trials:
                return
            self.study.optimize(self.objective, n_trials=1, catch=())

    def write_results(self) -> str:
        """trials.md, best.yaml and the plots in the study directory; the closing line."""
        self.directory.mkdir(parents=True, exist_ok=True)
        (self.directory / "trials.md").write_text(self.trials_table())
        written = ["trials.md"]
        completed = self.study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))
        if not completed:
            return f"otgb tune: no trial completed; results in {self.directory}: {', '.join(written)}"
        best = self.study.best_trial
        if self._write_best(best):
            written.append("best.yaml")
        written += self._plots()
        settings = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in best.params.items())
        return (
            f"otgb tune: best of {len(completed)} completed trials: trial {best.number}, {self.monitor} {best.value:.4g} "
            f"with {settings}; results in {self.directory}: {', '.join(written)}"
        )

    def trials_table(self) -> str:
        keys = list(self.space)
        lines = [
            f"# Study {self.name}: {self.monitor}, lower is better",
            "",
            f"| trial | state | {self.monitor} | " + " | ".join(keys) + " | wall time | run | note |",
            "|---" * (len(keys) + 6) + "|",
        ]
        for t in self.study.get_trials(deepcopy=False):
            score = f"{t.value:.4g}" if t.value is not None else "-"
            params = [f"{t.params[k]:.4g}" if isinstance(t.params.get(k), float) else str(t.params.get(k, "-")) for k in keys]
            wall = f"{t.user_attrs['wall_s'] / 60:.1f} min" if "wall_s" in t.user_attrs else "-"
            note = t.user_attrs.get("failed_because", "")
            if self.baseline and all(t.params.get(k) == v for k, v in self.baseline.items()):
                note = f"the config's own settings{'; ' + note if note else ''}"
            if t.state == optuna.trial.TrialState.PRUNED and t.intermediate_values:
                step = max(t.intermediate_values)
                note = f"pruned at step {step} ({self.monitor} {t.intermediate_values[step]:.4g})"
            run = t.user_attrs.get("run_dir", "-")
            lines.append(
                f"| {t.number} | {t.state.name.lower()} | {score} | " + " | ".join(params) + f" | {wall} | {run} | {note} |"
            )
        return "\n".join(lines) + "\n"

    def _write_best(self, best: optuna.trial.FrozenTrial) -> bool:
        """The best trial's config.yaml, its loggers renamed so that a refit goes to runs/tune-<name>-best."""
        source = Path(best.user_attrs.get("run_dir", "")) / "config.yaml"
        if not source.is_file():
            return False
        config = yaml.safe_load(source.read_text())
        for logger in config.get("trainer", {}).get("logger") or []:
            logger.setdefault("init_args", {}).update(save_dir="runs", name=f"tune-{self.name}-best", version=None)
        header = f"# Study {self.name}, best trial {best.number}: {self.monitor} {best.value:.6g}. otgb fit --config best.yaml\n"
        (self.directory / "best.yaml").write_text(header + yaml.safe_dump(config, sort_keys=False))
        return True

    def _plots(self) -> list[str]:
        written = []
        plots = {"history.png": optuna.visualization.matplotlib.plot_optimization_history}
        if len(self.space) > 1:
            plots["importances.png"] = optuna.visualization.matplotlib.plot_param_importances
        for name, plot in plots.items():
            with warnings.catch_warnings():  # from one completed trial Optuna draws every importance equal: no figure
                warnings.filterwarnings("error", message=".*importances will be equal")
                try:
                    figure = plot(self.study).figure
                except (ValueError, RuntimeError, UserWarning):  # too few completed trials for an importance
                    continue
            figure.set_size_inches(10, 4.5)  # room for the config keys' full names
            figure.tight_layout()
            save(figure, self.directory / name)
            close(figure)
            written.append(name)
        return written


def _monitor(config: Any) -> str:
    return config.get("checkpoint.monitor") or "auto"


def tune(argv: list[str]) -> Path:
    """Run ``otgb tune`` with its arguments; returns the study directory."""
    settings, configs, overrides = parse(argv)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    # Optuna marks the stale-trial check and its matplotlib plots experimental: a note about its API, not the study.
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    study = Study(settings, configs, overrides)
    study.optimize()
    print(study.write_results())
    return study.directory
