"""Measured trajectories on their own times, placed on one grid of observation times.

A lab records each trajectory at its own times: a camera's frames with some dropped, a run
stopped early, a logger's irregular stamps. :func:`on_common_times` places them all on one
grid, the sorted union of the times any trajectory was measured at, with NaN wherever a
trajectory has no value (a missing value: not measured at that time, or measured but lost).

- When every measured time is one of the model's observation times (to 1e-6 of the model's
  horizon), the grid is the model's own: an early stop or a dropped frame is NaN there, and the
  model is solved and read exactly as for a complete file.
- Otherwise the grid is the union of the file's times and the model is read at them
  (:meth:`otgb.physics.PhysicsModel.read_at`): its own step, interpolated inside a step.

Every measured time must lie within the model's horizon, [0, the model's last observation
time]; each trajectory needs at least :data:`MIN_SAMPLES` measured times with a value; a
trajectory's times must increase. Each problem is one line naming the file, the trajectory
and the time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from otgb.errors import InputError
from otgb.physics.base import PhysicsModel

MIN_SAMPLES = 3  # measured times with a value per trajectory: fewer say nothing about a trajectory's course
UNIT_FACTORS = (1e-3, 1e3, 60.0, 1 / 60, 3600.0, 1 / 3600, 1e-6, 1e6)  # s <-> ms, min, h, us: times in another unit


@dataclass(frozen=True)
class CommonTimes:
    """Trajectories on one grid: ``y`` (N, T, *obs) with NaN where missing, ``times`` (T,) where they are not the
    model's observation times (None: they are, and y is on the model's grid), and the recorded inputs ``u`` (N, T, I)
    on the same grid, NaN where missing (None: none recorded)."""

    y: Tensor
    times: Tensor | None
    u: Tensor | None = None


def on_common_times(
    where: str, y: Tensor, t: Tensor | None, ids: list[str], physics: PhysicsModel, u: Tensor | None = None
) -> CommonTimes:
    """Place trajectories ``y`` (N, T, *obs) measured at ``t`` on one grid (the module docstring), and the inputs ``u``
    (N, T, I) recorded beside them (in the order of the model's ``input_names``) with them.

    ``t`` is None (the model's observation times), (T,) shared by every trajectory or (N, T), each row a
    trajectory's own times with NaN after its last (a shorter trajectory, padded); ``y`` is NaN where ``t`` is.
    ``ids`` names the trajectories in errors.
    """
    if u is not None:
        _check_inputs(where, u, y, ids, physics)
    model_times = physics.observation_times().double()
    if t is None:
        if y.shape[1] != len(model_times):
            expected = f"(N, {len(model_times)}, {', '.join(map(str, physics.obs_shape))})"
            raise InputError(
                f"{where}: 'y': measured trajectories have shape {tuple(y.shape)}, expected {expected} on the model's "
                f"{len(model_times)} times (or give their times 't')"
            )
        _check_samples(where, y, ids)
        return CommonTimes(y.float(), None, None if u is None else u.float())
    times = _per_trajectory_times(where, t.double(), len(y), y.shape[1])
    _check_times(where, times, y, ids, physics, model_times)
    grid = _model_grid_index(times, model_times)
    union = model_times if grid is not None else torch.from_numpy(np.unique(times[torch.isfinite(times)].numpy()))
    index = grid if grid is not None else torch.searchsorted(union, times.nan_to_num(float(union[-1])))
    rows, present = torch.arange(len(y))[:, None].expand_as(index), torch.isfinite(times)

    def place(values: Tensor) -> Tensor:
        placed = torch.full((len(values), len(union), *values.shape[2:]), float("nan"), dtype=torch.float32)
        placed[rows[present], index[present]] = values[present].float()
        return placed

    placed = place(y)
    _check_samples(where, placed, ids)
    return CommonTimes(placed, None if grid is not None else union, None if u is None else place(u))


def _check_inputs(where: str, u: Tensor, y: Tensor, ids: list[str], physics: PhysicsModel) -> None:
    """Recorded inputs: (N, T, I) beside y, finite or NaN (missing), at least one value of each per trajectory."""
    names = tuple(physics.input_names)
    if tuple(u.shape) != (*y.shape[:2], len(names)):
        raise InputError(
            f"{where}: 'u' has shape {tuple(u.shape)}, expected ({y.shape[0]}, {y.shape[1]}, {len(names)}): the inputs "
            f"{names} recorded at each time of 'y'"
        )
    if bool(torch.isinf(u).any()):
        row, _, column = (int(i) for i in torch.isinf(u).nonzero()[0])
        raise InputError(f"{where}: trajectory {ids[row]}: '{names[column]}' is infinite, expected finite numbers (NaN: missing)")
    never = torch.isnan(u).all(dim=1)
    if bool(never.any()):
        row, column = (int(i) for i in never.nonzero()[0])
        raise InputError(
            f"{where}: trajectory {ids[row]} has no recorded value of '{names[column]}', expected at least one (the input "
            "is read linearly between its recorded values)"
        )


def _per_trajectory_times(where: str, t: Tensor, n: int, steps: int) -> Tensor:
    """The times as (N, T): a shared (T,) row repeated, or the (N, T) given."""
    if t.dim() == 1 and len(t) == steps:
        return t[None].expand(n, steps)
    if t.dim() == 2 and tuple(t.shape) == (n, steps):
        return t
    raise InputError(
        f"{where}: 't' has shape {tuple(t.shape)}, expected ({steps},) (the times of every trajectory) or ({n}, {steps}) "
        "(each trajectory's own, NaN after its last)"
    )


def _check_times(
    where: str, times: Tensor, y: Tensor, ids: list[str], physics: PhysicsModel, model_times: Tensor
) -> None:  # fmt: skip
    """Times are finite or NaN (padding, with no value), increase within a trajectory and lie in the model's horizon."""
    if bool(torch.isinf(times).any()):
        row = int(torch.isinf(times).any(dim=1).nonzero()[0])
        raise InputError(f"{where}: trajectory {ids[row]}: a time is infinite, expected finite times")
    valued = torch.isfinite(y.reshape(*y.shape[:2], -1)).any(dim=2)
    padded_with_value = torch.isnan(times) & valued
    if bool(padded_with_value.any()):
        row = int(padded_with_value.any(dim=1).nonzero()[0])
        raise InputError(f"{where}: trajectory {ids[row]}: a value without a time (NaN in 't'), expected a time per value")
    for row in range(len(times)):
        own = times[row][torch.isfinite(times[row])]
        steps = torch.diff(own)
        if bool((steps <= 0).any()):
            k = int((steps <= 0).nonzero()[0])
            raise InputError(
                f"{where}: trajectory {ids[row]}: times not increasing, t={float(own[k + 1]):.6g} after t={float(own[k]):.6g}; "
                "expected each trajectory's times in increasing order, each once"
            )
    horizon, tol = float(model_times[-1]), 1e-6 * max(float(model_times[-1]), 1.0)
    outside = torch.isfinite(times) & ((times < -tol) | (times > horizon + tol))
    if bool(outside.any()):
        row = int(outside.any(dim=1).nonzero()[0])
        time = float(times[row][outside[row]][0])
        raise InputError(
            f"{where}: trajectory {ids[row]}: t={time:.6g} lies outside the model's horizon [0, {horizon:.6g}] "
            f"(physics dt={physics.dt:g}, n_obs={physics.n_obs}){_horizon_hint(times, physics, horizon)}"
        )


def _horizon_hint(times: Tensor, physics: PhysicsModel, horizon: float) -> str:
    """Why times may lie outside the horizon: another unit (an even step that is the model's dt times a usual unit
    factor), or a longer recording than the model's n_obs covers."""
    finite = times[torch.isfinite(times)]
    latest = float(finite.max())
    first_row = times[0][torch.isfinite(times[0])]
    if len(first_row) >= 2:
        step = torch.diff(first_row)
        if torch.allclose(step, step[:1].expand_as(step), rtol=1e-6, atol=1e-9 * latest):
            ratio = float(step[0]) / physics.dt
            if any(abs(ratio / factor - 1) < 1e-5 for factor in UNIT_FACTORS):
                unit = f" (the model's is {physics.units['t']})" if "t" in physics.units else ""
                return f": the file's step is {ratio:.6g} x the model's dt, in another unit?{unit}"
    needed = int(np.ceil(latest / physics.dt - 1e-6)) + (1 if physics.include_initial else 0)
    return f": the measurements last until t={latest:.6g}; set data.physics.init_args.n_obs to {needed} to cover them"


def _model_grid_index(times: Tensor, model_times: Tensor) -> Tensor | None:
    """Each time's index on the model's grid (NaN times: 0) where every finite time is one of the model's observation
    times, else None."""
    tol = 1e-6 * max(float(model_times[-1]), 1.0)
    finite = torch.isfinite(times)
    index = torch.searchsorted(model_times, times.nan_to_num(0.0) - tol).clamp(max=len(model_times) - 1)
    on_grid = (model_times[index] - times).abs() <= tol
    return index if bool(on_grid[finite].all()) else None


def _check_samples(where: str, y: Tensor, ids: list[str]) -> None:
    """Each trajectory has at least :data:`MIN_SAMPLES` times with a value; no value is infinite."""
    flat = y.reshape(*y.shape[:2], -1)
    if bool(torch.isinf(flat).any()):
        row = int(torch.isinf(flat).any(dim=(1, 2)).nonzero()[0])
        raise InputError(
            f"{where}: trajectory {ids[row]}: an infinite value, expected finite numbers (NaN or an empty cell: missing)"
        )
    counts = torch.isfinite(flat).any(dim=2).sum(dim=1)
    few = counts < MIN_SAMPLES
    if bool(few.any()):
        row = int(few.nonzero()[0])
        raise InputError(
            f"{where}: trajectory {ids[row]} has {int(counts[row])} measured time(s) with a value, expected at least "
            f"{MIN_SAMPLES} ({int(few.sum())} of {len(y)} trajectories have fewer)"
        )
