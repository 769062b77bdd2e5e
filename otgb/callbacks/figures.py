"""Figures logged at each validation: generated vs measured vs f_p.

Joint mode (a known DGP), for fixed validation inputs:

- :class:`TrajectoryFigure`: curves over time of one observed component (ODE systems).
- :class:`FieldFigure`: fields over space (PDE systems): the space-time image of a 1-D field,
  or a 2-D field at a few frames.

Marginal mode (measurements from a file), both callbacks draw :func:`distribution_figure`
instead: nothing is paired, so the sources are compared as distributions over time (quantile
bands and a few sample paths), saved as ``distributions_step<N>.png``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from lightning import Callback, LightningModule, Trainer  # noqa: E402
from lightning.pytorch.loggers import TensorBoardLogger  # noqa: E402

from otgb.physics.base import PhysicsModel  # noqa: E402


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
        if datamodule.mode == "marginal":
            tag, figure = "distributions", self._distributions(datamodule, pl_module)
        else:
            data = {k: v[: self.n_inputs].to(pl_module.device) for k, v in datamodule.val_set.items()}
            y_hat = pl_module.generate(data["x"], data["x0"], data["theta"], data["y"].shape[1]).cpu()
            data = {k: v.cpu() for k, v in data.items()}
            tag, figure = self.tag, self.draw(data, y_hat, datamodule.physics)
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_figure(f"val/{tag}", figure, global_step=trainer.global_step, close=False)
        if log_dir is not None:
            out = Path(log_dir) / "figures"
            out.mkdir(parents=True, exist_ok=True)
            figure.savefig(out / f"{tag}_step{trainer.global_step:07d}.png", dpi=80)
        plt.close(figure)

    def _distributions(self, datamodule, pl_module: LightningModule) -> plt.Figure:
        """Measured vs generated vs f_p as distributions over time, for the whole validation set (nothing is paired)."""
        data, chunk = datamodule.val_set, datamodule.eval_batch_size
        y_hat = torch.cat(
            [
                pl_module.generate(*(data[k][i : i + chunk].to(pl_module.device) for k in ("x", "x0", "theta")), 1).cpu()
                for i in range(0, len(data["x"]), chunk)
            ]
        )
        physics = datamodule.physics
        samples = {"measured": data["y"][:, 0], "generated": y_hat[:, 0], "f_p": data["x"]}
        return distribution_figure(samples, physics.observation_times(), list(physics.observed))

    def draw(self, data: dict[str, torch.Tensor], y_hat: torch.Tensor, physics: PhysicsModel) -> plt.Figure:
        """data: the joint set's rows (x (N, T, *obs), y (N, M, T, *obs), theta, x0); y_hat (N, M, T, *obs)."""
        raise NotImplementedError


BAND_STYLE = {"measured": ("black", "-"), "generated": ("tab:green", "-"), "f_p": ("tab:orange", "--")}


def probe_series(trajectories: torch.Tensor, names: Sequence[str]) -> tuple[torch.Tensor, list[str]]:
    """(N, T, C, *space) or (N, T, C) -> (N, T, K) series and their labels.

    ODE observations give one series per component; fields one per channel at up to three
    cells along the grid's diagonal (a quarter, half and three quarters of the way).
    """
    channels, space = trajectories.shape[2], trajectories.shape[3:]
    if not space:
        return trajectories, list(names)
    fractions = (0.25, 0.5, 0.75)
    cells = sorted({tuple(min(int(f * size), size - 1) for size in space) for f in fractions})
    series = torch.stack([trajectories[(slice(None), slice(None), c, *cell)] for c in range(channels) for cell in cells], dim=-1)
    labels = [f"{names[c]} at cell {cell}" for c in range(channels) for cell in cells]
    return series, labels


def distribution_figure(samples: dict[str, torch.Tensor], times: torch.Tensor, names: Sequence[str]) -> plt.Figure:
    """Median, 25-75 % and 5-95 % bands over time of each source, and three sample paths each.

    ``samples``: source name -> trajectories (N, T, *obs) (the sources may differ in N).
    """
    series = {name: probe_series(values.float(), names) for name, values in samples.items()}
    labels = next(iter(series.values()))[1]
    cols = min(len(labels), 3)
    rows = -(-len(labels) // cols)
    figure, axes = plt.subplots(rows, cols, figsize=(4.5 * cols, 2.8 * rows), squeeze=False)
    t = times.numpy()
    for k, ax in enumerate(axes.flat):
        if k >= len(labels):
            ax.axis("off")
            continue
        for source, (values, _) in series.items():
            colour, style = BAND_STYLE.get(source, ("tab:blue", "-"))
            q = torch.quantile(values[..., k], torch.tensor([0.05, 0.25, 0.5, 0.75, 0.95]), dim=0).numpy()
            ax.fill_between(t, q[0], q[4], color=colour, alpha=0.12, lw=0)
            ax.fill_between(t, q[1], q[3], color=colour, alpha=0.25, lw=0)
            ax.plot(t, q[2], color=colour, ls=style, lw=1.5, label=f"{source} (n={len(values)})")
            for path in values[:3, :, k]:
                ax.plot(t, path.numpy(), color=colour, ls=style, lw=0.5, alpha=0.6)
        ax.set_title(labels[k], fontsize=8)
        ax.set_xlabel("t", fontsize=7)
    axes.flat[0].legend(fontsize=7)
    figure.suptitle("median, 25-75 % and 5-95 % bands, 3 sample paths each (unpaired)", fontsize=8)
    figure.tight_layout()
    return figure


def _theta_label(physics: PhysicsModel, theta: torch.Tensor) -> str:
    return ", ".join(f"{name}={v:.3g}" for name, v in zip(physics.theta_names, theta.tolist()))


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

    def draw(self, data: dict[str, torch.Tensor], y_hat: torch.Tensor, physics: PhysicsModel) -> plt.Figure:
        n = len(y_hat)
        cols = min(n, 3)
        rows = -(-n // cols)
        figure, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.6 * rows), squeeze=False)
        t = physics.observation_times().numpy()
        c = self.component
        for i, ax in enumerate(axes.flat):
            if i >= n:
                ax.axis("off")
                continue
            y, x = data["y"][i], data["x"][i]
            ax.plot(t, x[:, c].flatten(), color="grey", ls="--", lw=1, label="f_p")
            for j in range(y.shape[0]):
                ax.plot(t, y[j, :, c].flatten(), color="black", lw=1, alpha=0.6, label="measured" if j == 0 else None)
                ax.plot(t, y_hat[i, j, :, c].flatten(), color="tab:green", lw=1, alpha=0.8, label="generated" if j == 0 else None)
            ax.set_title(_theta_label(physics, data["theta"][i]), fontsize=8)
        axes.flat[0].legend(fontsize=7)
        figure.tight_layout()
        return figure


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
    SOURCES = ("measured", "generated", "f_p")

    def __init__(self, n_inputs: int = 2, channel: int = 0, frames: Sequence[int] | None = None) -> None:
        super().__init__(n_inputs)
        self.channel, self.frames = channel, None if frames is None else list(frames)

    def draw(self, data: dict[str, torch.Tensor], y_hat: torch.Tensor, physics: PhysicsModel) -> plt.Figure:
        channels = data["x"].shape[2]
        if not 0 <= self.channel < channels:
            raise ValueError(f"FieldFigure.channel={self.channel}: the observed field has {channels} channel(s)")
        fields = {"measured": data["y"][:, 0], "generated": y_hat[:, 0], "f_p": data["x"]}
        fields = {k: v[:, :, self.channel] for k, v in fields.items()}  # (N, T, *space)
        space_dims = fields["measured"].dim() - 2
        if space_dims == 1:
            return self._space_time(fields, data["theta"], physics)
        if space_dims == 2:
            return self._frames(fields, data["theta"], physics)
        raise ValueError(f"FieldFigure draws 1-D or 2-D fields, got {space_dims} spatial dimensions")

    def _space_time(self, fields: dict, theta: torch.Tensor, physics: PhysicsModel) -> plt.Figure:
        n = len(theta)
        figure, axes = plt.subplots(n, 4, figsize=(13, 2.6 * n), squeeze=False)
        extent = (0.0, float(physics.times()[-1]), 0.0, 1.0)  # time across, space (grid index / size) up
        for i in range(n):
            low = min(float(f[i].min()) for f in fields.values())
            high = max(float(f[i].max()) for f in fields.values())
            panels = [(name, fields[name][i], "viridis", low, high) for name in self.SOURCES]
            diff = fields["generated"][i] - fields["measured"][i]
            scale = float(diff.abs().max()) or 1.0
            panels.append(("generated - measured", diff, "RdBu_r", -scale, scale))
            for ax, (name, field, cmap, vmin, vmax) in zip(axes[i], panels):
                image = ax.imshow(field.T, aspect="auto", origin="lower", cmap=cmap, vmin=vmin, vmax=vmax, extent=extent)
                ax.set_title(f"{name} ({_theta_label(physics, theta[i])})", fontsize=7)
                ax.set_xlabel("t", fontsize=7)
                ax.set_yticks([])
                figure.colorbar(image, ax=ax)
        figure.tight_layout()
        return figure

    def _frames(self, fields: dict, theta: torch.Tensor, physics: PhysicsModel) -> plt.Figure:
        steps = fields["measured"].shape[1]
        frames = self.frames if self.frames is not None else sorted({0, steps // 3, 2 * steps // 3, steps - 1})
        if any(not 0 <= f < steps for f in frames):
            raise ValueError(f"FieldFigure.frames={frames}: expected indices in [0, {steps})")
        times = physics.observation_times()
        n = len(theta)
        figure, axes = plt.subplots(3 * n, len(frames), figsize=(2.2 * len(frames), 2.2 * 3 * n), squeeze=False)
        for i in range(n):
            low = min(float(f[i].min()) for f in fields.values())
            high = max(float(f[i].max()) for f in fields.values())
            for r, name in enumerate(self.SOURCES):
                for c, frame in enumerate(frames):
                    ax = axes[3 * i + r, c]
                    ax.imshow(fields[name][i, frame], cmap="viridis", vmin=low, vmax=high)
                    ax.set_xticks([])
                    ax.set_yticks([])
                    ax.set_title(f"{name}, t={float(times[frame]):.2g}", fontsize=7)
            axes[3 * i, 0].set_ylabel(_theta_label(physics, theta[i]), fontsize=6)
        figure.tight_layout()
        return figure
