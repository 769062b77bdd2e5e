"""The progress bar: counts to the run's real end and shows the simulations spent against the budget."""

from __future__ import annotations

from typing import Any

from lightning import LightningModule, Trainer
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import convert_inf


class SimulationProgressBar(TQDMProgressBar):
    """Lightning's progress bar plus ``simulations: used/budget`` (over all processes).

    Its total is where training ends: ``max_steps`` or the simulation budget (the length of
    otgb's source stream), whichever comes first, counted from the run's start (also when resumed).
    """

    @property
    def total_train_batches(self) -> int | float:
        total, max_steps = super().total_train_batches, self.trainer.max_steps
        return min(total, max_steps) if max_steps is not None and max_steps >= 0 else total

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Set the total already here: a run resumed within its (single) epoch gets no epoch start."""
        super().on_train_start(trainer, pl_module)
        self.train_progress_bar.reset(total=convert_inf(self.total_train_batches))
        self.train_progress_bar.set_description(f"Epoch {trainer.current_epoch}")

    def get_metrics(self, trainer: Trainer, pl_module: LightningModule) -> dict[str, Any]:
        metrics = super().get_metrics(trainer, pl_module)
        datamodule = trainer.datamodule
        if hasattr(datamodule, "simulations") and hasattr(datamodule, "simulation_budget"):
            metrics["simulations"] = f"{datamodule.simulations}/{datamodule.simulation_budget}"
        return metrics
