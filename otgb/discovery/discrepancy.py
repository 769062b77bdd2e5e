"""The discrepancy between a simulated and a measured sample of trajectories: the unbiased energy distance between
whole trajectories plus that between the values at each time step, with the per-row terms that a comparison's
standard error needs.

Where measured values are missing (NaN), the simulated trajectories take the measured sample's gaps (row i those of
measured row i mod m) and both samples are 0 there (:mod:`otgb.data.gaps`). A time step's distance is then the
distance between the values measured there times the square of the share measured (a point mass at 0 of the same
weight on both sides adds nothing else), so it is 0 exactly where the measured values' distributions agree."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from otgb.data.gaps import comparable, filled, has_gaps
from otgb.metrics.energy import (
    batched_energy,
    cell_and_whole_row_means,
    cell_and_whole_within_means,
    cross_row_means,
    within_means,
)


def discrepancy(a: Tensor, b: Tensor) -> Tensor:
    """Energy distance between trajectories a (n, T, *obs) and b (m, T, *obs): over whole trajectories
    plus the sum over time steps and components of the distances between their values there.

    The second part compares the marginal distributions at each time (a spread that grows or
    shrinks over time, as an effect that varies between trajectories makes it), which the
    distance between whole trajectories detects with far less power.
    """
    return discrepancy_and_rows(a, Target.of(b))[0]


def batched_discrepancy(a: Tensor, b: Tensor) -> Tensor:
    """:func:`discrepancy` of each pair a[g] (n, T, *obs), b[g] (m, T, *obs): (G,)."""
    if has_gaps(b):
        a, b = torch.stack([comparable(a_g, b_g)[0] for a_g, b_g in zip(a, b)]), filled(b)
    whole = batched_energy(a.flatten(2), b.flatten(2))
    cells = lambda y: _cells(y.flatten(0, 1)).unflatten(1, y.shape[:2]).transpose(0, 1).flatten(0, 1)  # noqa: E731
    per_cell = batched_energy(cells(a), cells(b)).reshape(len(a), -1)
    return whole + per_cell.sum(1)


def _cells(y: Tensor) -> Tensor:
    """Trajectories (n, T, C, *space) as (T * C, n, space): one sample per time step and component."""
    return y.reshape(len(y), y.shape[1] * y.shape[2], -1).transpose(0, 1)


@dataclass
class Target:
    """Measured trajectories y (m, T, *obs) and their within-sample mean distances, whole (a number) and per cell
    (T * C,): every :func:`discrepancy` to them shares these, so they are computed once."""

    y: Tensor  # 0 where a value is missing
    whole: Tensor
    cells: Tensor
    gaps: Tensor | None = None  # the measured trajectories with NaN where a value is missing; None: none is

    @classmethod
    def of(cls, y: Tensor) -> Target:
        gaps = y if has_gaps(y) else None
        y = filled(y)
        whole, cells = _within(y)
        return cls(y, whole, cells, gaps)

    def as_measured(self, a: Tensor) -> Tensor:
        """Simulated trajectories a with this sample's gaps, 0 there (:mod:`otgb.data.gaps`)."""
        return a if self.gaps is None else comparable(a, self.gaps)[0]


def discrepancy_and_rows(a: Tensor, target: Target) -> tuple[Tensor, Tensor]:
    """:func:`discrepancy` of a to the target and, per target trajectory, its share of the cross terms
    (:func:`row_terms`), from one set of distances."""
    a = target.as_measured(a)
    whole, cells = _cross(a, target.y)  # (m,), (T * C, m)
    within_whole, within_cells = _within(a)
    value = 2 * whole.mean() - within_whole - target.whole
    value = value + (2 * cells.mean(-1) - within_cells - target.cells).sum()
    return value, 2 * (whole + cells.sum(0))


def _cross(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Each trajectory of b's mean distance to a's, whole (m,) and per cell (T * C, m). On fields, both from one
    product per cell (:func:`otgb.metrics.energy.cell_and_whole_row_means`); a cell of one number is sorted."""
    if _on_fields(a):
        cells, whole = cell_and_whole_row_means(_cells(a), _cells(b))
        return whole, cells
    return cross_row_means(a.flatten(1)[None], b.flatten(1)[None])[0], cross_row_means(_cells(a), _cells(b))


def _within(y: Tensor) -> tuple[Tensor, Tensor]:
    """Mean distance between y's distinct trajectories, whole (a number) and per cell (T * C,), as :func:`_cross`."""
    if _on_fields(y):
        cells, whole = cell_and_whole_within_means(_cells(y))
        return whole, cells
    return within_means(y.flatten(1)[None])[0], within_means(_cells(y))


def _on_fields(y: Tensor) -> bool:
    """Whether a cell of y (n, T, C, *space) (one time step and component) holds more than one number."""
    return math.prod(y.shape[3:]) > 1


def row_terms(a: Tensor, b: Tensor) -> Tensor:
    """Per trajectory of b, its share of :func:`discrepancy`'s cross terms: twice its mean distance to
    a's trajectories, whole and per cell, summed: (m,)."""
    a, b = comparable(a, b) if has_gaps(b) else (a, b)
    whole = cross_row_means(a.flatten(1)[None], b.flatten(1)[None])[0]
    return 2 * (whole + cross_row_means(_cells(a), _cells(b)).sum(0))
