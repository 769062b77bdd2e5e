"""The progress bar: counts to the run's real end and shows the simulations spent against the budget."""

from __future__ import annotations

import math
import sys
from time import perf_counter
from typing import Any

from lightning import LightningModule, Trainer
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import convert_inf


class SimulationProgressBar(TQDMProgressBar):
    """Lightning's progress bar plus ``simulations: used/budget`` (over all processes).

    Its total is where training ends: ``max_steps`` or the simulation budget (the length of
    otgb's source stream), whichever comes first, counted from the run's start (also when resumed).

    ``lines``: write the progress as plain lines, :data:`LINES` of them per run, instead of a bar
    redrawn in place. ``None`` (default): lines when the output is not a terminal (a log file, a
    batch job, a captured notebook cell), where a bar's redraws pile up into one long line.
    """

    LINES = 20  # progress lines in a run of known length

    def __init__(self, *args: Any, lines: bool | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.lines = lines
        self._started, self._first_step = 0.0, 0
        self._since: tuple[float, int] | None = None  # the clock and step of the first line: the rate is counted from it

    @property
    def writes_lines(self) -> bool:
        return self.lines if self.lines is not None else not sys.stdout.isatty()

    @property
    def is_disabled(self) -> bool:
        """Lightning's bars stay hidden while the progress is written as lines."""
        return super().is_disabled or self.writes_lines

    @property
    def total_train_batches(self) -> int | float:
        total, max_steps = super().total_train_batches, self.trainer.max_steps
        return min(total, max_steps) if max_steps is not None and max_steps >= 0 else total

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Set the total already here: a run resumed within its (single) epoch gets no epoch start."""
        super().on_train_start(trainer, pl_module)
        self.train_progress_bar.reset(total=convert_inf(self.total_train_batches))
        self.train_progress_bar.set_description(f"Epoch {trainer.current_epoch}")
        self._started, self._first_step = perf_counter(), trainer.global_step  # a resumed run starts past 0
        self._since = None

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, *args: Any, **kwargs: Any) -> None:
        """The bar's update, or a line every 1/:data:`LINES` of the run (the metrics, read back from the device, only
        then: the hidden bar would read them at every step)."""
        if not self.writes_lines:
            return super().on_train_batch_end(trainer, pl_module, *args, **kwargs)
        total, step = self.total_train_batches, trainer.global_step
        every = max(1, math.ceil(total / self.LINES)) if math.isfinite(total) else 100
        if self.is_enabled and (step % every == 0 or step == total):
            print(self.progress_line(step, total, self.get_metrics(trainer, pl_module)), flush=True)

    def progress_line(self, step: int, total: int | float, metrics: dict[str, Any]) -> str:
        """``step 100/1000 (10%) | 1m04s, about 9m36s to go | simulations 1600/16000 | loss_T -0.0123``.

        The time to go is at the rate since the first line, once there is one: what a run pays once at its start
        (compiling its solves, scoring f_p alone and the Reference at the first validation) is not paid again."""
        now = perf_counter()
        elapsed = now - self._started
        where = f"step {step}/{total} ({100 * step / total:.0f}%)" if math.isfinite(total) else f"step {step}"
        since, first = self._since or (self._started, self._first_step)
        self._since = self._since or (now, step)
        done = step - first
        if math.isfinite(total) and done > 0 and step < total:
            where += f" | {_clock(elapsed)}, about {_clock((now - since) * (total - step) / done)} to go"
        shown = [f"{name} {value:.4g}" if isinstance(value, float) else f"{name} {value}" for name, value in metrics.items()]
        return " | ".join([where, *[m for m in shown if not m.startswith("v_num ")]])

    def get_metrics(self, trainer: Trainer, pl_module: LightningModule) -> dict[str, Any]:
        metrics = super().get_metrics(trainer, pl_module)
        datamodule = trainer.datamodule
        if hasattr(datamodule, "simulations") and hasattr(datamodule, "simulation_budget"):
            metrics["simulations"] = f"{datamodule.simulations}/{datamodule.simulation_budget}"
        return metrics


def _clock(seconds: float) -> str:
    """``42s``, ``9m36s``, ``1h05m``."""
    minutes, seconds = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{seconds:02d}s" if minutes else f"{seconds}s"
