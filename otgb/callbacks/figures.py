"""Figures logged at each validation: generated vs measured vs f_p.

Joint mode (a known DGP), for fixed validation inputs:

- :class:`TrajectoryFigure`: curves over time of one observed component (ODE systems).
- :class:`FieldFigure`: fields over space (PDE systems): the space-time image of a 1-D field,
  or a 2-D field at a few frames.

Marginal mode (measurements from a file), both callbacks draw :func:`otgb.analysis.figures.distribution_figure`
instead: nothing is paired, so the sources are compared as distributions over time (quantile
bands and a few sample paths), saved as ``distributions_step<N>.png``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib.pyplot as plt
import torch
from lightning import Callback, LightningModule, Trainer
from lightning.pytorch.loggers import TensorBoardLogger

from otgb.analysis.figures import close, distribution_figure, frames_figure, save, space_time_figure, trajectory_figure
from otgb.physics.base import PhysicsModel


class ValidationFigure(Callback):
    """Draws the first ``n_inputs`` validation inputs after each validation (rank 0 only).

    The figure goes to TensorBoard (tag ``val/<tag>``) and to
    ``<log_dir>/figures/<tag>_step<global_step>.png``. Subclasses define :meth:`draw`.

    Args:
        n_inputs: validation inputs drawn (the first ones of the validation set).
    """

    tag = "figure"

    def __init__(self, n_inputs: int) -> None:
        if n_inputs < 1:
            raise ValueError(f"{type(self).__name__}: n_inputs={n_inputs}, expected >= 1")
        self.n_inputs = n_inputs

    @torch.no_grad()
    def on_validation_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.sanity_checking:
            return
        log_dir = trainer.log_dir  # a collective call under DDP: every process makes it
        if not trainer.is_global_zero:
            return
        datamodule = trainer.datamodule
        if not datamodule.source.draws_pair_with_inputs:
            tag, figure = "distributions", self._distributions(datamodule, pl_module, trainer.global_step)
        else:
            data = {k: v[: self.n_inputs].to(pl_module.device) for k, v in datamodule.val_set.items()}
            y_hat = pl_module.generate(
                data["x"], data["x0"], data["theta"], data["y"].shape[1], signals=data.get("signals")
            ).cpu()
            data = {k: v.cpu() for k, v in data.items()}
            tag, figure = self.tag, self.draw(data, y_hat, datamodule.physics, trainer.global_step)
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_figure(f"val/{tag}", figure, global_step=trainer.global_step, close=False)
        if log_dir is not None:
            out = Path(log_dir) / "figures"
            out.mkdir(parents=True, exist_ok=True)
            save(figure, out / f"{tag}_step{trainer.global_step:07d}.png")
        close(figure)

    def _distributions(self, datamodule, pl_module: LightningModule, step: int) -> plt.Figure:
        """Measured vs generated vs f_p as distributions over time, for the whole validation set (nothing is paired)."""
        data, chunk = datamodule.val_set, datamodule.eval_batch_size
        rows = lambda key, i: None if key not in data else data[key][i : i + chunk].to(pl_module.device)  # noqa: E731
        y_hat = torch.cat(
            [
                pl_module.generate(*(rows(k, i) for k in ("x", "x0", "theta")), 1, signals=rows("signals", i)).cpu()
                for i in range(0, len(data["x"]), chunk)
            ]
        )
        physics = datamodule.physics
        samples = {"measured": data["y"][:, 0], "generated": y_hat[:, 0], "f_p": data["x"]}
        names = [physics.axis_label(name) for name in physics.observed]
        return distribution_figure(samples, physics.observation_times(), names, step, physics.axis_label("t"))

    def draw(self, data: dict[str, torch.Tensor], y_hat: torch.Tensor, physics: PhysicsModel, step: int) -> plt.Figure:
        """data: the joint set's rows (x (N, T, *obs), y (N, M, T, *obs), theta, x0); y_hat (N, M, T, *obs)."""
        raise NotImplementedError


class TrajectoryFigure(ValidationFigure):
    """Measured draws, the map's draws and the f_p simulation of one observed component over time.

    Args:
        n_inputs: validation inputs drawn, one panel each.
        component: index of the observed component shown (e.g. 0 = the angle).
    """

    tag = "trajectories"

    def __init__(self, n_inputs: int = 6, component: int = 0) -> None:
        super().__init__(n_inputs)
        self.component = component

    def draw(self, data: dict[str, torch.Tensor], y_hat: torch.Tensor, physics: PhysicsModel, step: int) -> plt.Figure:
        return trajectory_figure(data, y_hat, physics, self.component, step)


class FieldFigure(ValidationFigure):
    """Measured, generated (first draw) and f_p fields of one channel, on one colour scale per input.

    A 1-D field (obs (C, X)) is shown as a space-time image per source, with the generated
    minus measured difference beside it; a 2-D field (obs (C, X, Y)) at the observed
    ``frames`` (indices into the trajectory), one row per source.

    Args:
        n_inputs: validation inputs drawn, one row each.
        channel: the field shown (e.g. 0 = u).
        frames: frame indices for 2-D fields (default: four spread over the trajectory).
    """

    tag = "fields"

    def __init__(self, n_inputs: int = 2, channel: int = 0, frames: Sequence[int] | None = None) -> None:
        super().__init__(n_inputs)
        self.channel, self.frames = channel, None if frames is None else list(frames)

    def draw(self, data: dict[str, torch.Tensor], y_hat: torch.Tensor, physics: PhysicsModel, step: int) -> plt.Figure:
        channels = data["x"].shape[2]
        if not 0 <= self.channel < channels:
            raise ValueError(f"FieldFigure.channel={self.channel}: the observed field has {channels} channel(s)")
        fields = {"measured": data["y"][:, 0], "generated": y_hat[:, 0], "f_p": data["x"]}
        fields = {k: v[:, :, self.channel] for k, v in fields.items()}  # (N, T, *space)
        name, space_dims = physics.observed[self.channel], fields["measured"].dim() - 2
        if space_dims == 1:
            return space_time_figure(fields, data["theta"], physics, name, step)
        if space_dims == 2:
            steps = fields["measured"].shape[1]
            frames = self.frames if self.frames is not None else sorted({0, steps // 3, 2 * steps // 3, steps - 1})
            if any(not 0 <= f < steps for f in frames):
                raise ValueError(f"FieldFigure.frames={frames}: expected indices in [0, {steps})")
            return frames_figure(fields, data["theta"], physics, frames, name, step)
        raise ValueError(f"FieldFigure draws 1-D or 2-D fields, got {space_dims} spatial dimensions")
