"""The callback that runs the grey-box's component analysis (:mod:`otgb.analysis.components`) when ``otgb fit`` ends
its training, and writes ``components.json`` and ``figures/components.png`` into the run directory."""

from __future__ import annotations

import json
from pathlib import Path

from lightning import Callback, LightningModule, Trainer
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_warn

from otgb.analysis.components import component_analysis, to_json
from otgb.analysis.figures import close, components_figure, save
from otgb.errors import InputError


class ComponentAnalysis(Callback):
    """Runs :func:`component_analysis` once, when ``otgb fit`` ends its training (rank 0 only).

    Writes ``<log_dir>/components.json`` (:func:`component_analysis`'s result) and
    ``<log_dir>/figures/components.png``, adds the figure to TensorBoard and logs
    ``components/<name>`` for each summary float (``traj_err``, ``traj_err_fp``, ``func_err``, ``func_err_fp``,
    ``correction_share``; the function-level ones only where available) to every logger. It
    runs at ``on_train_end``, while the module is still on its training device (Lightning
    moves it to the CPU before ``on_fit_end``). A map without components (not a grey-box) is
    skipped with a warning.

    Args:
        n: Validation inputs analysed (the first ones of the validation set); at least 2.
        seed: Seed of the analysis' latent draws z.
        enabled: Whether to run the analysis at the end of training.
    """

    def __init__(self, n: int = 64, seed: int = 0, enabled: bool = True) -> None:
        if n < 2:
            raise InputError(f"components.n={n}: expected >= 2 validation inputs")
        self.n, self.seed, self.enabled = n, seed, enabled

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        log_dir = trainer.log_dir  # a collective call under DDP: every process makes it
        if not self.enabled or not trainer.is_global_zero:
            return
        if not hasattr(pl_module.evaluation_map(), "components"):
            rank_zero_warn(f"ComponentAnalysis: {type(pl_module.evaluation_map()).__name__} has no components(); skipped")
            return
        result = component_analysis(pl_module, trainer.datamodule, self.n, self.seed)
        scalars = {f"components/{k}": v for k, v in result["summary"].items() if v is not None}
        figure = components_figure(result, trainer.global_step)
        for logger in trainer.loggers:
            logger.log_metrics(scalars, step=trainer.global_step)
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_figure("components", figure, global_step=trainer.global_step, close=False)
        if log_dir is not None:
            out = Path(log_dir)
            (out / "figures").mkdir(parents=True, exist_ok=True)
            (out / "components.json").write_text(json.dumps(to_json(result), indent=1))
            save(figure, out / "figures" / "components.png")
        close(figure)
