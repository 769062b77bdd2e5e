"""Figures that compare sources (measured, generated, f_p, an augmented physics) by eye.

Every figure has axis labels, a legend or colour bar, and a title saying what it shows and at
which training step; comparisons that a reader judges by eye share one scale; figures are saved
at :data:`DPI` and at least :data:`MIN_WIDTH_PX` pixels wide (:func:`save`). The callbacks
(:mod:`otgb.callbacks`) and ``otgb discover`` (:mod:`otgb.discovery.report`) draw with these.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.colors as colors  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from torch import Tensor  # noqa: E402

from otgb.physics.base import PhysicsModel  # noqa: E402

DPI = 150
MIN_WIDTH_PX = 800
STYLE = {"measured": ("black", "-"), "generated": ("tab:green", "-"), "f_p": ("tab:orange", "--"), "augmented": ("tab:blue", "-")}


def save(figure: plt.Figure, path: Path) -> None:
    """Save at :data:`DPI`, widened to :data:`MIN_WIDTH_PX` pixels where it is narrower."""
    width, height = figure.get_size_inches()
    if width * DPI < MIN_WIDTH_PX:
        figure.set_size_inches(MIN_WIDTH_PX / DPI, height * MIN_WIDTH_PX / (DPI * width))
    figure.savefig(path, dpi=DPI)


def close(figure: plt.Figure) -> None:
    plt.close(figure)


TITLE_CHARS_PER_INCH = 12  # characters of a 9-point title per inch of figure width, with a margin


def title(figure: plt.Figure, what: str, step: int | None = None) -> None:
    """The figure's title, ``what`` and the training step, wrapped to the figure's width (never cut at its edges);
    "training step N" stays on one line."""
    text = what if step is None else f"{what}, training\u00a0step\u00a0{step}"
    width = max(40, int(figure.get_figwidth() * TITLE_CHARS_PER_INCH))
    figure.suptitle(textwrap.fill(text, width).replace("\u00a0", " "), fontsize=9)


def theta_label(physics: PhysicsModel, theta: Tensor) -> str:
    """Each theta with its unit where the model declares one: "omega=1.23 rad/s, ..."."""
    return ", ".join(f"{name}={v:.3g}{_unit(physics, name)}" for name, v in zip(physics.theta_names, theta.tolist()))


def _unit(physics: PhysicsModel, name: str) -> str:
    """The unit to write after a value of ``name`` (" rad/s"), or "" where the model declares none."""
    return f" {physics.units[name]}" if name in physics.units else ""


def probe_series(trajectories: Tensor, names: Sequence[str]) -> tuple[Tensor, list[str]]:
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


LEGEND_BELOW = 0.6  # inches under the distribution figure's panels for its legend's two rows


def distribution_figure(
    samples: dict[str, Tensor], times: Tensor, names: Sequence[str], step: int | None = None, time_label: str = "t"
) -> plt.Figure:  # fmt: skip
    """Median, 25-75 % and 5-95 % bands over time of each source, and two sample paths each, on one y scale per
    series. ``samples``: source name -> trajectories (N, T, *obs) (the sources may differ in N); ``names``: the
    observed components' axis labels (with their units, :meth:`otgb.physics.PhysicsModel.axis_label`). The first
    source's bands are filled, the others' outlined (25-75 % solid, 5-95 % dotted), so that overlapping bands stay
    apart."""
    series = {name: probe_series(values.float(), names) for name, values in samples.items()}
    labels = next(iter(series.values()))[1]
    cols = min(len(labels), 3)
    rows = -(-len(labels) // cols)
    height = 3.0 * rows + 0.6 + LEGEND_BELOW
    figure, axes = plt.subplots(rows, cols, figsize=(max(4.5 * cols, 8.0), height), squeeze=False)
    t = times.numpy()
    for k, ax in enumerate(axes.flat):
        if k >= len(labels):
            ax.axis("off")
            continue
        for i, (source, (values, _)) in enumerate(series.items()):
            colour, style = STYLE.get(source, ("tab:purple", "-"))
            q = torch.nanquantile(values[..., k], torch.tensor([0.05, 0.25, 0.5, 0.75, 0.95]), dim=0).numpy()
            if i == 0:
                ax.fill_between(t, q[0], q[4], color=colour, alpha=0.10, lw=0)
                ax.fill_between(t, q[1], q[3], color=colour, alpha=0.22, lw=0)
            else:
                for edge, line in ((0, ":"), (1, "-"), (3, "-"), (4, ":")):
                    ax.plot(t, q[edge], color=colour, ls=line, lw=0.8)
            ax.plot(t, q[2], color=colour, ls=style, lw=1.8, label=f"{source} (n={len(values)})")
            for path in values[:2, :, k].numpy():
                _plot_path(ax, t, path, color=colour, ls=style, lw=0.5, alpha=0.45)
        ax.set_title(labels[k], fontsize=8)
        ax.set_xlabel(time_label, fontsize=8)
        ax.set_ylabel(labels[k], fontsize=8)
    first = next(iter(series))
    styles = [  # what each line and band is, in grey, after the sources' colours
        Line2D([], [], color="grey", lw=1.8, label="median (thick)"),
        Patch(color="grey", alpha=0.3, label=f"{first}: 25-75 % and 5-95 % (filled)"),
        Line2D([], [], color="grey", lw=0.8, label="others: 25-75 % (solid), 5-95 % (dotted)", ls="-"),
        Line2D([], [], color="grey", lw=0.5, alpha=0.6, label="2 sample paths (thin)"),
    ]
    handles = axes.flat[0].get_legend_handles_labels()[0] + styles
    figure.legend(handles=handles, fontsize=7, loc="lower center", ncol=4, frameon=False)  # below the panels, off the data
    what = f"median, 25-75 % and 5-95 % over time ({first} filled), 2 paths each (unpaired)"
    if any(bool(torch.isnan(values).any()) for values, _ in series.values()):
        what += "; with missing values, each time's bands over the trajectories measured there, measured paths as dots"
    title(figure, what, step)
    figure.tight_layout(rect=(0, LEGEND_BELOW / height, 1, 1))
    return figure


def _plot_path(ax: plt.Axes, t: np.ndarray, path: np.ndarray, **style: Any) -> None:
    """One trajectory over time: a line, or its measured points as dots where some values are missing (NaN)."""
    measured = ~np.isnan(path)
    if measured.all():
        ax.plot(t, path, **style)
    else:
        ax.plot(t[measured], path[measured], ".", ms=2.5, **{k: v for k, v in style.items() if k not in ("ls", "lw")})


def trajectory_figure(
    data: dict[str, Tensor], y_hat: Tensor, physics: PhysicsModel, component: int, step: int | None = None
) -> plt.Figure:  # fmt: skip
    """Measured draws, the map's draws and the f_p simulation of one observed component over time, one panel per
    input, all panels on one y scale. ``data``: the joint set's rows (x, y, theta); ``y_hat`` (N, M, T, *obs)."""
    n, name = len(y_hat), physics.observed[component]
    cols = min(n, 3)
    rows = -(-n // cols)
    figure, axes = plt.subplots(rows, cols, figsize=(max(4 * cols, 6.0), 2.8 * rows + 0.6), squeeze=False, sharey=True)
    t = physics.observation_times().numpy()
    for i, ax in enumerate(axes.flat):
        if i >= n:
            ax.axis("off")
            continue
        y, x = data["y"][i], data["x"][i]
        ax.plot(t, x[:, component].flatten(), color="tab:orange", ls="--", lw=1, label="f_p")
        for j in range(y.shape[0]):
            measured, generated = ("measured", "generated") if j == 0 else (None, None)
            _plot_path(ax, t, y[j, :, component].flatten().numpy(), color="black", lw=1, alpha=0.6, label=measured)
            ax.plot(t, y_hat[i, j, :, component].flatten(), color="tab:green", lw=1, alpha=0.8, label=generated)
        ax.set_title(theta_label(physics, data["theta"][i]), fontsize=8)
        ax.set_xlabel(physics.axis_label("t"), fontsize=7)
        ax.set_ylabel(physics.axis_label(name), fontsize=7)
    axes.flat[0].legend(fontsize=7)
    title(figure, f"{name}: measured, generated and f_p for {n} validation inputs", step)
    figure.tight_layout()
    return figure


def space_time_figure(
    fields: dict[str, Tensor], theta: Tensor, physics: PhysicsModel, channel: str, step: int | None = None
) -> plt.Figure:  # fmt: skip
    """Space-time images of a 1-D field per source (one colour scale per input) and generated minus measured.
    ``fields``: source -> (N, T, X)."""
    n = len(theta)
    figure, axes = plt.subplots(n, 4, figsize=(13, 2.8 * n + 0.6), squeeze=False)
    extent = (0.0, float(physics.times()[-1]), 0.0, 1.0)  # time across, position (fraction of the domain) up
    for i in range(n):
        low = min(float(f[i].min()) for f in fields.values())
        high = max(float(f[i].max()) for f in fields.values())
        panels = [(name, fields[name][i], "viridis", low, high) for name in ("measured", "generated", "f_p")]
        diff = fields["generated"][i] - fields["measured"][i]
        scale = float(diff.abs().max()) or 1.0
        panels.append(("generated - measured", diff, "RdBu_r", -scale, scale))
        for ax, (name, field, cmap, vmin, vmax) in zip(axes[i], panels):
            image = ax.imshow(field.T, aspect="auto", origin="lower", cmap=cmap, vmin=vmin, vmax=vmax, extent=extent)
            ax.set_title(f"{name} ({theta_label(physics, theta[i])})", fontsize=7)
            ax.set_xlabel(physics.axis_label("t"), fontsize=7)
            ax.set_ylabel("position (fraction of the domain)", fontsize=6)
            figure.colorbar(image, ax=ax, label=physics.axis_label(channel))
    title(figure, f"{channel}: measured, generated and f_p over space and time", step)
    figure.tight_layout()
    return figure


def frames_figure(
    fields: dict[str, Tensor], theta: Tensor, physics: PhysicsModel, frames: Sequence[int], channel: str,
    step: int | None = None,
) -> plt.Figure:  # fmt: skip
    """A 2-D field at ``frames``, one row per source, one colour scale per input. ``fields``: source -> (N, T, X, Y)."""
    times, unit = physics.observation_times(), _unit(physics, "t")
    n = len(theta)
    sources = ("measured", "generated", "f_p")
    figure, axes = plt.subplots(3 * n, len(frames), figsize=(max(2.4 * len(frames), 6.0), 2.4 * 3 * n + 0.6), squeeze=False)
    for i in range(n):
        low = min(float(f[i].min()) for f in fields.values())
        high = max(float(f[i].max()) for f in fields.values())
        for r, name in enumerate(sources):
            for c, frame in enumerate(frames):
                ax = axes[3 * i + r, c]
                image = ax.imshow(fields[name][i, frame], cmap="viridis", vmin=low, vmax=high)
                ax.set_title(f"{name}, t={float(times[frame]):.2g}{unit}", fontsize=7)
                ax.set_xlabel("y (cell)", fontsize=6)
                ax.set_ylabel("x (cell)", fontsize=6)
                ax.tick_params(labelsize=5)
        label = f"{physics.axis_label(channel)} ({theta_label(physics, theta[i])})"
        figure.colorbar(image, ax=axes[3 * i : 3 * i + 3, :].ravel().tolist(), label=label)
    title(figure, f"{channel}: measured, generated and f_p at {len(frames)} frames", step)
    return figure


def components_figure(result: dict[str, Any], step: int | None = None) -> plt.Figure:
    """Panels over time: trajectory-level error, function-level errors (where a true vector field is known; else a
    line below says why they are missing), |f_p| and |f_phi| (:func:`otgb.analysis.components.component_analysis`'s
    result)."""
    t = result["times"].numpy()
    known = result["func_err"] is not None
    figure, axes = plt.subplots(1, 3 if known else 2, figsize=(13 if known else 9, 3.6))
    traj, parts = axes[0], axes[-1]
    kind = "ABS ERR" if result["traj_err_kind"] == "abs_err" else "energy distance"
    traj.plot(t, result["traj_err_fp"].numpy(), color="tab:orange", ls="--", label="f_p vs measured")
    traj.plot(t, result["traj_err"].numpy(), color="tab:green", label="grey-box vs measured")
    traj.set_title(f"trajectory level ({kind})", fontsize=9)
    traj.set_ylabel(kind, fontsize=8)
    traj.legend(fontsize=7)
    if known:
        func = axes[1]
        func.plot(t, result["func_err_fp"].numpy(), color="tab:orange", ls="--", label="f_p")
        func.plot(t, result["func_err"].numpy(), color="tab:green", label="f_p + f_phi")
        func.legend(fontsize=7)
        func.set_title("function level: mean |f - f_true|", fontsize=9)
        func.set_ylabel("mean |f - f_true|", fontsize=8)
    parts.plot(t, result["f_p_abs"].numpy(), color="tab:orange", ls="--", label="|f_p|")
    parts.plot(t, result["f_phi_abs"].numpy(), color="tab:green", label="|f_phi|")
    parts.set_title(f"components along the solve (f_phi share {result['summary']['correction_share']:.3g})", fontsize=9)
    parts.set_ylabel("mean |f|", fontsize=8)
    parts.legend(fontsize=7)
    for ax in axes:
        ax.set_xlabel(result["time_label"], fontsize=8)
    title(figure, "component analysis of the grey-box along its solve", step)
    if known:
        figure.tight_layout()
    else:
        figure.text(0.5, 0.01, f"function level not shown: {result['func_err_unavailable']}", ha="center", fontsize=7)
        figure.tight_layout(rect=(0, 0.05, 1, 1))
    return figure


def disagreement_figure(maps: list[tuple[Any, str]], time_label: str = "t") -> plt.Figure:
    """Disagreement maps (:class:`otgb.discovery.locate.DisagreementMap`) side by side on one scale, so that the
    gap's shrinking is seen: curves per component (ODE) or a heatmap over (time, component x region) (fields);
    ``time_label``: the time axis's label, with its unit."""
    figure, axes = plt.subplots(1, len(maps), figsize=(6.5 * len(maps), 3.8), squeeze=False, sharey=True)
    top = max(float(m.statistic.max()) for m, _ in maps) or 1.0
    bottom = min(0.0, *(float(m.statistic.min()) for m, _ in maps))  # the unbiased distance dips below 0 by chance
    for ax, (disagreement, panel_title) in zip(axes[0], maps):
        _draw_disagreement(ax, disagreement, panel_title, top, bottom)
        ax.set_xlabel(time_label)
    title(figure, "energy distance between the model's simulations and the measurements (dots: significant)")
    figure.tight_layout()
    return figure


def _draw_disagreement(ax: plt.Axes, result: Any, title: str, top: float, bottom: float) -> None:
    times = result.times.numpy()
    if len(result.regions) == 1:
        for c, name in enumerate(result.components):
            stat, sig = result.statistic[:, c, 0].numpy(), result.significant[:, c, 0].numpy()
            (line,) = ax.plot(times, stat, label=name)
            if sig.any():
                ax.plot(times[sig], stat[sig], "o", color=line.get_color(), ms=4, label=f"{name}: significant")
        ax.set_ylim(bottom, 1.05 * top)  # one scale for all panels (the axes are shared)
        ax.set_ylabel("energy distance per time step")
        ax.legend(fontsize=7)
    else:
        values = result.statistic.flatten(1).T.numpy()  # (C * R, T)
        image = ax.imshow(
            values, aspect="auto", origin="lower", cmap="viridis", norm=colors.PowerNorm(0.5, vmin=0, vmax=top),
            extent=(times[0], times[-1], -0.5, values.shape[0] - 0.5), interpolation="nearest",
        )  # fmt: skip
        rows, cols = np.nonzero(result.significant.flatten(1).T.numpy())
        step = (times[-1] - times[0]) / max(len(times) - 1, 1)
        ax.plot(times[0] + cols * step, rows, "r.", ms=3, label="significant")
        labels = [f"{comp} {reg}" for comp in result.components for reg in result.regions]
        ax.set_yticks(range(len(labels)), labels, fontsize=5)
        ax.set_ylabel("component and region")
        if len(rows):
            ax.legend(fontsize=7, loc="upper right")
        ax.figure.colorbar(image, ax=ax, label="energy distance")
    ax.tick_params(labelleft=True)  # each panel its numbers: the shared scale is read on every one
    whole = "differ" if result.whole_significant else "no difference seen"  # a difference no single cell shows
    ax.set_title(f"{title}\nwhole trajectories: {whole} (permutation p = {result.whole_pvalue:.2g})", fontsize=9)
