"""Figures logged at each validation: generated vs measured trajectories for fixed inputs."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from lightning import Callback, LightningModule, Trainer  # noqa: E402
from lightning.pytorch.loggers import TensorBoardLogger  # noqa: E402


class TrajectoryFigure(Callback):
    """Plots, for the first ``n_inputs`` validation inputs, the measured draws, the map's
    draws and the f_p simulation of the first observed component over time.

    The figure goes to TensorBoard (tag ``val/trajectories``) and to
    ``<log_dir>/figures/val_step<global_step>.png``.
    """

    def __init__(self, n_inputs: int = 6, component: int = 0) -> None:
        self.n_inputs, self.component = n_inputs, component

    @torch.no_grad()
    def on_validation_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        data = {k: v[: self.n_inputs].to(pl_module.device) for k, v in trainer.datamodule.val_set.items()}
        y_hat = pl_module.generate(data["x"], data["x0"], data["theta"], data["y"].shape[1]).cpu()
        figure = self.draw(data, y_hat, trainer.datamodule.physics)
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_figure("val/trajectories", figure, global_step=trainer.global_step, close=False)
        if trainer.log_dir is not None:
            out = Path(trainer.log_dir) / "figures"
            out.mkdir(parents=True, exist_ok=True)
            figure.savefig(out / f"val_step{trainer.global_step:07d}.png", dpi=80)
        plt.close(figure)

    def draw(self, data: dict, y_hat: torch.Tensor, physics) -> plt.Figure:
        n = len(y_hat)
        cols = min(n, 3)
        rows = -(-n // cols)
        figure, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.6 * rows), squeeze=False)
        t = physics.times()[-physics.n_obs :].numpy()
        c = self.component
        for i, ax in enumerate(axes.flat):
            if i >= n:
                ax.axis("off")
                continue
            y, x = data["y"][i].cpu(), data["x"][i].cpu()
            ax.plot(t, x[:, c].flatten(), color="grey", ls="--", lw=1, label="f_p")
            for j in range(y.shape[0]):
                ax.plot(t, y[j, :, c].flatten(), color="black", lw=1, alpha=0.6, label="measured" if j == 0 else None)
                ax.plot(t, y_hat[i, j, :, c].flatten(), color="tab:green", lw=1, alpha=0.8, label="generated" if j == 0 else None)
            theta = ", ".join(f"{name}={v:.2f}" for name, v in zip(physics.theta_names, data["theta"][i].tolist()))
            ax.set_title(theta, fontsize=8)
        axes.flat[0].legend(fontsize=7)
        figure.tight_layout()
        return figure
