"""Locate: where and when do two samples of trajectories disagree?

For every cell (time step, observed component, spatial region) the two samples' values in
that cell are compared by the energy distance (Szekely & Rizzo, "Energy statistics: A class
of statistics based on distances"), its p-value comes from permutations of the sample labels
(the same permutations for every cell), and the cells that disagree are those kept by the
Benjamini-Hochberg procedure ("Controlling the false discovery rate", 1995; scipy's
``false_discovery_control``) at level ``alpha``. :func:`describe` turns the map into a plain
sentence; :func:`draw` into a figure.

Where measured values are missing (NaN), the model's trajectories take the measured sample's gaps
(:mod:`otgb.data.gaps`) and both samples are 0 there: a cell's test then compares the trajectories
measured in it, with an equal point mass at 0 on both sides, and stays exact under the permutations
(values missing at random, not because of what they would have been). Its distance is that of the
measured values times the square of the share measured there; a cell with fewer than two measured
values holds nothing to compare (statistic 0, p-value 1), and one with few has little power. The
summaries (mean, spread, amplitude) are over the measured values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy.stats import false_discovery_control
from torch import Tensor

from otgb.data.gaps import filled, observed, with_gaps_of
from otgb.discovery.paired import PairedCheck

DISTANCE_BYTES = 2**29  # the cells' distance matrices held at once, at most (at least one cell's)
SPREAD_FLOOR = 1e-3  # of the features' RMS spread: a feature (nearly) constant in both samples is not blown up to unit spread


@dataclass(frozen=True)
class DisagreementMap:
    """Per-cell statistics of two samples, each (T, C, R): time steps, components, regions.

    ``statistic`` is the energy distance (in the observation's units), ``pvalue`` its
    permutation p-value, ``significant`` the cells kept at false discovery rate ``alpha``.
    ``whole_*``: the same test between whole trajectories, each feature (time step, component, cell)
    z-scored with the pooled samples' mean and standard deviation, as the gap table's energy distance
    (:func:`otgb.metrics.energy.energy_distance`): a difference spread thinly over many cells, one in
    how the steps of a trajectory go together, or one late in a decaying trajectory, where the
    values are small, shows there first (in the observation's units, the large early values would
    drown it). The pooled z-score does not depend on the labels, so the permutation test stays exact. ``alpha`` is
    split between the two families: the cells at false discovery rate alpha / 2, the whole
    trajectories at level alpha / 2.
    ``mean_*`` / ``spread_*`` / ``amplitude_*`` are each sample's mean, standard deviation and
    mean absolute value per cell (averaged over the region), for the sentence; ``sizes`` the two
    samples' numbers of trajectories; ``drawn_from`` the measured part's size where ``a`` is a random
    subset of it (0: all of it).
    """

    times: Tensor
    components: tuple[str, ...]
    regions: list[str]
    statistic: Tensor
    pvalue: Tensor
    significant: Tensor
    alpha: float
    n_permutations: int
    mean_a: Tensor
    mean_b: Tensor
    spread_a: Tensor
    spread_b: Tensor
    amplitude_a: Tensor
    amplitude_b: Tensor
    whole_statistic: float = 0.0
    whole_pvalue: float = 1.0
    whole_significant: bool = False
    sizes: tuple[int, int] = (0, 0)  # trajectories in a (the measurements) and in b (the model's)
    whole_level: float = 0.025  # the level of the whole-trajectory test (and of the paired check, when there is one)
    paired: PairedCheck | None = None  # f_p on the measurements' recorded inputs (otgb.discovery.paired)
    drawn_from: int = 0  # the measured trajectories a was drawn from at random; 0: a is all of them

    @property
    def measured_trajectories(self) -> str:
        """The measured trajectories tested, for a title: "1000 of its 5250 trajectories, drawn at random" or "140
        trajectories"."""
        drawn = f" of its {self.drawn_from}" if self.drawn_from else ""
        return f"{self.sizes[0]}{drawn} trajectories{', drawn at random' if drawn else ''}"

    @property
    def any_significant(self) -> bool:
        return bool(self.significant.any()) or self.whole_significant or self.paired_significant

    @property
    def paired_significant(self) -> bool:
        return self.paired is not None and self.paired.significant

    def to_dict(self) -> dict:
        return {
            "times": self.times.tolist(),
            "components": list(self.components),
            "regions": self.regions,
            "alpha": self.alpha,
            "n_permutations": self.n_permutations,
            "significant_cells": int(self.significant.sum()),
            "cells": int(self.significant.numel()),
            "statistic": self.statistic.tolist(),
            "pvalue": self.pvalue.tolist(),
            "significant": self.significant.tolist(),
            "whole": {"statistic": self.whole_statistic, "pvalue": self.whole_pvalue, "significant": self.whole_significant},
            "whole_level": self.whole_level,
            "paired": None if self.paired is None else self.paired.to_dict(),
            "sizes": list(self.sizes),
            "drawn_from": self.drawn_from,
        }


def region_slices(grid_shape: tuple[int, ...], per_axis: int) -> list[tuple[tuple[slice, ...], str]]:
    """Contiguous blocks of a grid, ``per_axis`` along each axis, with labels like ``s 0-4``."""
    if not grid_shape:
        return [((), "all")]
    axes = []
    for size in grid_shape:
        edges = np.linspace(0, size, min(per_axis, size) + 1).round().astype(int)
        axes.append([(slice(a, b), f"{a}-{b - 1}") for a, b in zip(edges[:-1], edges[1:])])
    names = ["s"] if len(grid_shape) == 1 else ["x", "y", "z"][: len(grid_shape)]
    blocks = [((), "")]
    for name, parts in zip(names, axes):
        blocks = [(index + (s,), f"{label} {name} {text}".strip()) for index, label in blocks for s, text in parts]
    return blocks


def cell_values(y: Tensor, grid_shape: tuple[int, ...], per_axis: int) -> tuple[Tensor, list[str]]:
    """Trajectories (n, T, C, *grid) -> per-cell vectors (T * C * R, n, cells of a region), region labels."""
    blocks = region_slices(grid_shape, per_axis)
    parts = [y[(..., *index)].flatten(3) if grid_shape else y.unsqueeze(-1) for index, _ in blocks]
    sizes = {p.shape[-1] for p in parts}
    if len(sizes) > 1:  # unequal blocks: pad with zeros in both samples alike (distances unchanged)
        width = max(sizes)
        parts = [torch.nn.functional.pad(p, (0, width - p.shape[-1])) for p in parts]
    stacked = torch.stack(parts, dim=3)  # (n, T, C, R, width)
    return stacked.flatten(1, 3).transpose(0, 1).double(), [label for _, label in blocks]


def permutation_energy(a: Tensor, b: Tensor, n_permutations: int, seed: int) -> tuple[Tensor, Tensor]:
    """Unbiased energy distance per cell and its permutation p-value: a (G, n, d), b (G, m, d) -> (G,), (G,)."""
    n, m = a.shape[1], b.shape[1]
    labels = permutation_labels(n, n + m, n_permutations, seed)
    stats, block = [], max(1, DISTANCE_BYTES // (8 * (n + m) ** 2))
    for start in range(0, len(a), block):
        pooled = torch.cat([a[start : start + block], b[start : start + block]], dim=1)
        distances = torch.cdist(pooled, pooled)  # (g, N, N)
        total = distances.sum((1, 2))[:, None]
        row_a = distances @ labels.T  # (g, N, K+1): distance of each point to sample a's points
        within_a = torch.einsum("kn,gnk->gk", labels, row_a)
        cross = torch.einsum("kn,gnk->gk", 1 - labels, row_a)
        within_b = total - 2 * cross - within_a
        stats.append(2 * cross / (n * m) - within_a / (n * (n - 1)) - within_b / (m * (m - 1)))
    stats = torch.cat(stats)  # (G, K+1)
    observed = stats[:, 0]
    pvalue = (1 + (stats[:, 1:] >= observed[:, None] - 1e-12).sum(1)) / (n_permutations + 1)
    return observed, pvalue


def permutation_labels(n: int, total: int, n_permutations: int, seed: int) -> Tensor:
    """(n_permutations + 1, total) float64 indicators of the first sample: row 0 the observed labels (the first ``n``),
    then ``n_permutations`` random relabellings drawn with ``seed``."""
    g = torch.Generator().manual_seed(seed)
    labels = torch.zeros(n_permutations + 1, total, dtype=torch.float64)
    labels[0, :n] = 1
    for k in range(1, n_permutations + 1):
        labels[k, torch.randperm(total, generator=g)[:n]] = 1
    return labels


def z_scored(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Rows of both samples with each feature centred and scaled by the pooled samples' mean and standard deviation
    (over the values present: a missing one, NaN, is 0 afterwards); a spread below ``SPREAD_FLOOR`` of the features'
    RMS spread (a boundary value fixed in both, up to rounding) is raised to it, so that rounding does not weigh as
    much as a real feature."""
    pooled = torch.cat([a, b])
    mean, spread = pooled.nanmean(0), nan_std(pooled, 0).nan_to_num(0.0)
    floor = max(SPREAD_FLOOR * float(spread.pow(2).mean().sqrt()), 1e-300)
    spread = spread.clamp_min(floor)
    return filled((a - mean) / spread), filled((b - mean) / spread)


def nan_std(x: Tensor, dim: int | tuple[int, ...]) -> Tensor:
    """The standard deviation (n - 1 in the denominator) over ``dim`` of the values present (not NaN); NaN where fewer
    than two are."""
    present = observed(x)
    count = present.sum(dim, keepdim=True)
    centred = torch.where(present, x - x.nanmean(dim, keepdim=True), 0.0)
    variance = centred.pow(2).sum(dim, keepdim=True) / (count - 1).clamp_min(1)
    return variance.where(count > 1, float("nan")).sqrt().squeeze(dim)


def locate(
    a: Tensor,
    b: Tensor,
    times: Tensor,
    components: tuple[str, ...],
    n_permutations: int = 999,
    alpha: float = 0.05,
    regions_per_axis: int = 4,
    seed: int = 0,
    paired: PairedCheck | None = None,
) -> DisagreementMap:
    """Where samples ``a`` (n, T, C, *grid) and ``b`` (m, T, C, *grid) of trajectories disagree.

    Fields are split into ``regions_per_axis`` blocks per spatial axis; each (time, component,
    region) cell is tested. ``a`` is the reference side of the sentence (the measurements),
    ``b`` the model (f_p or a corrected model). With ``paired`` (f_p on a's recorded inputs), the
    whole-trajectory half of alpha is split between the whole-trajectory test and that check.
    """
    if a.dim() < 3 or a.shape[1:] != b.shape[1:]:
        raise ValueError(f"locate: expected trajectories (n, T, C, ...) of one shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    steps, channels, grid = a.shape[1], a.shape[2], tuple(a.shape[3:])
    b = with_gaps_of(b, a)  # the measured gaps on the model's side (module docstring)
    cells_a, regions = cell_values(a, grid, regions_per_axis)
    cells_b, _ = cell_values(b, grid, regions_per_axis)
    statistic, pvalue = permutation_energy(filled(cells_a), filled(cells_b), n_permutations, seed)
    whole_a, whole_b = z_scored(a.flatten(1).double(), b.flatten(1).double())
    whole, whole_pvalue = permutation_energy(whole_a[None], whole_b[None], n_permutations, seed)
    # two families, alpha split between them (Bonferroni): one whole-trajectory p-value inside the cells'
    # Benjamini-Hochberg set would need p < alpha / (cells + 1), below what the permutations can give
    significant = false_discovery_control(pvalue.numpy()) <= alpha / 2
    whole_level = alpha / 4 if paired is not None else alpha / 2
    whole_significant = bool(whole_pvalue[0] <= whole_level)
    if paired is not None:
        paired = replace(paired, significant=paired.pvalue <= whole_level)
    shape = (steps, channels, len(regions))
    summary = {}
    for side, cells in (("a", cells_a), ("b", cells_b)):
        summary[f"mean_{side}"] = cells.nanmean((1, 2)).reshape(shape).float()
        summary[f"spread_{side}"] = nan_std(cells, 1).nanmean(1).reshape(shape).float()
        summary[f"amplitude_{side}"] = cells.abs().nanmean((1, 2)).reshape(shape).float()
    return DisagreementMap(
        times=times.float().cpu(),
        components=tuple(components),
        regions=regions,
        statistic=statistic.reshape(shape).float(),
        pvalue=pvalue.reshape(shape).float(),
        significant=torch.from_numpy(significant).reshape(shape),
        alpha=alpha,
        n_permutations=n_permutations,
        **summary,
        whole_statistic=float(whole[0]),
        whole_pvalue=float(whole_pvalue[0]),
        whole_significant=whole_significant,
        sizes=(len(a), len(b)),
        whole_level=whole_level,
        paired=paired,
    )


def describe(result: DisagreementMap, a_name: str = "measured", b_name: str = "simulated") -> str:
    """A plain sentence: until when the samples agree, and how they differ afterwards, per component; and the paired
    check's figures, where there is one."""
    sentence = _distributions(result, a_name, b_name)
    if result.paired is None:
        return sentence
    if result.paired_significant and not (result.significant.any() or result.whole_significant):
        return f"{result.paired.sentence()}, though {sentence}"
    return f"{sentence}; {result.paired.sentence()}"


def _distributions(result: DisagreementMap, a_name: str, b_name: str) -> str:
    """:func:`describe`'s sentence on the two-sample tests alone."""
    if not (result.significant.any() or result.whole_significant):
        sentence = (
            f"the disagreement map's tests see no difference between {b_name} and {a_name} trajectories ({result.sizes[1]} and "
            f"{result.sizes[0]}{f' of {result.drawn_from}, drawn at random' if result.drawn_from else ''}): "
            f"neither the whole trajectories nor any time step, component or region differ at a false discovery rate of "
            f"{result.alpha:g} ({result.n_permutations} permutations)"
        )
        if result.whole_pvalue <= 2 * result.whole_level:  # significant on its own, not beside the other families
            sentence += (
                f"; the whole trajectories come close (permutation p = {result.whole_pvalue:.2g}, threshold "
                f"{result.whole_level:g}): a difference may be there that more measurements would show"
            )
        return sentence
    if not result.significant.any():
        return (
            f"{b_name} and {a_name} trajectories differ as a whole (energy distance of the z-scored trajectories "
            f"{result.whole_statistic:.3g}, "
            f"permutation p = {result.whole_pvalue:.3g}), though no single time step, component or region does"
        )
    times = result.times
    flagged = result.significant.any(2).any(1)
    first = onset(flagged)
    start = "differ from the start:"
    if first > 0:
        start = f"agree up to t = {times[first - 1]:.3g}{_earlier(flagged, first, times)}; from t = {times[first]:.3g} on"
    parts = [_component_difference(result, c, a_name, b_name) for c in range(len(result.components))]
    return f"{b_name} and {a_name} trajectories {start} " + "; ".join(p for p in parts if p)


def _earlier(flagged: Tensor, first: int, times: Tensor) -> str:
    """The flagged steps before the onset, as an aside: spans of two steps or more by their times, single steps by count
    (they can pass by chance, :func:`onset`)."""
    earlier = runs(flagged[:first])
    spans = [f"t = {times[begin]:.3g} to {times[end - 1]:.3g}" for begin, end in earlier if end - begin > 1]
    single = sum(end - begin == 1 for begin, end in earlier)
    spans += [f"{single} isolated earlier step{'s' if single > 1 else ''}"] if single else []
    return f" (apart from {' and '.join(spans)})" if spans else ""


def runs(flagged: Tensor) -> list[tuple[int, int]]:
    """The runs of consecutive flagged steps, as (first, one past the last) index pairs in time order."""
    found, start = [], None
    for i, value in enumerate([*flagged.tolist(), False]):
        if value and start is None:
            start = i
        elif not value and start is not None:
            found.append((start, i))
            start = None
    return found


def onset(flagged: Tensor) -> int:
    """The first time step of the longest run of flagged steps (the earliest of the longest).

    At a false discovery rate of alpha, about alpha of the flagged cells are null ones, and when
    most cells are truly different the Benjamini-Hochberg threshold nears alpha itself: a few
    early steps (neighbours, so alike) can pass by chance. The longest run is where the
    disagreement sets in.
    """
    return max(runs(flagged), key=lambda run: (run[1] - run[0], -run[0]))[0]


def _component_difference(result: DisagreementMap, c: int, a_name: str, b_name: str) -> str:
    """How sample a differs from b in component c over its significant cells (the largest relative change)."""
    cells = result.significant[:, c]
    if not cells.any():
        return ""
    name = result.components[c]
    pick = lambda v: v[:, c][cells]  # noqa: E731
    spread = pick(result.spread_a).mean(), pick(result.spread_b).mean()
    amplitude = pick(result.amplitude_a).mean(), pick(result.amplitude_b).mean()
    shift = (pick(result.mean_a) - pick(result.mean_b)).mean()
    scale = max(float(spread[1]), 1e-12)
    changes = {
        "amplitude": math.log(max(float(amplitude[0]), 1e-12) / max(float(amplitude[1]), 1e-12)),
        "spread": math.log(max(float(spread[0]), 1e-12) / scale),
        "mean": float(shift) / scale,
    }
    kind = max(changes, key=lambda k: abs(changes[k]))
    if kind == "mean":
        what = f"mean is {'higher' if shift > 0 else 'lower'} (by {abs(float(shift)):.3g})"
    else:
        values = amplitude if kind == "amplitude" else spread
        label = "amplitude (mean |value|)" if kind == "amplitude" else "spread across trajectories"
        what = f"{label} is {'larger' if changes[kind] > 0 else 'smaller'} ({float(values[0]):.3g} vs {float(values[1]):.3g})"
    where = _where(result, c)
    return f"the {a_name} {name}'s {what}{where}, in {int(cells.sum())} of {cells.numel()} cells"


def _where(result: DisagreementMap, c: int) -> str:
    if len(result.regions) == 1:
        return ""
    strongest = result.statistic[:, c].sum(0).argmax()
    return f", most in region {result.regions[int(strongest)]}"
