"""Reading a user's file of measured trajectories: ``.pt``, ``.npz`` or ``.csv``.

What a file holds (names as the physics model declares them):

- ``y`` (required): the measured trajectories, (N, T, *obs_shape), e.g. (N, 50, 1) for the
  pendulum's angle at t = 0, 0.1, ..., 4.9, or (N, 50, 1, 20) for an advection-diffusion field;
  NaN is a missing value;
- ``t`` (optional): the observation times, (T,) for every trajectory or (N, T) for each its own
  (NaN after a shorter trajectory's last time); without it, the model's observation times;
- ``theta`` (optional): the physics parameters each trajectory was recorded with, (N, P), in
  the order of the model's ``theta_names``;
- ``x0`` (optional): each trajectory's full initial state, (N, *state_shape);
- ``u`` (optional): inputs recorded beside the states, (N, T, I) at the times of ``y``, in the order of
  the model's ``input_names`` (the pendulum's ``drive``); NaN is a missing value, read linearly
  between the recorded ones. A model driven this way needs no other setting.

``.pt``: a tensor (``y``) or a dict of tensors with those keys. ``.npz``: arrays with those
keys. ``.csv`` (low-dimensional series only): the long layout, one row per trajectory and
time, with a header

    trajectory, t, <observed variables>[, <input names>][, <theta names>][, x0_<state variables>]

e.g. ``trajectory,t,angle,omega`` for the pendulum with recorded omega, ``trajectory,t,angle,drive``
with its recorded drive (one value per row, like the observed ones). Rows of one trajectory
share its id, each trajectory has its own times (any number, in increasing order) and an
empty cell or NaN in an observed column is a missing value; the per-trajectory columns (theta,
x0_*) must be constant within it.

Trajectories on their own times are placed on one grid of times (:mod:`otgb.data.times`): the
model's own where every time is one of its observation times, else the union of the file's.

Every problem is an :class:`otgb.errors.InputError` naming the file, what was found and what
was expected. The file is only read, never written.
"""

from __future__ import annotations

import csv
import difflib
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from otgb.data.times import on_common_times
from otgb.errors import InputError, first_line
from otgb.physics.base import PhysicsModel

KEYS = ("y", "t", "theta", "x0", "u")
SUFFIXES = (".pt", ".npz", ".csv")


@dataclass(frozen=True)
class MeasuredFile:
    """The validated content of a measurement file: y (N, T, *obs) with NaN where a value is missing, the times ``times``
    (T,) it is on where they are not the model's observation times (None: they are), the recorded map inputs
    (theta, x0) if any, and the recorded input signals ``u`` (N, T, I) on the same times, NaN where missing."""

    path: str
    y: Tensor
    theta: Tensor | None = None
    x0: Tensor | None = None
    times: Tensor | None = None
    u: Tensor | None = None

    def __len__(self) -> int:
        return len(self.y)

    @property
    def recorded_inputs(self) -> tuple[str, ...]:
        """Which map inputs the file recorded: a subset of ("theta", "x0"), in that order."""
        return tuple(name for name in ("theta", "x0") if getattr(self, name) is not None)

    def subset(self, index: Tensor) -> MeasuredFile:
        pick = lambda v: None if v is None else v[index]  # noqa: E731
        return replace(self, y=self.y[index], theta=pick(self.theta), x0=pick(self.x0), u=pick(self.u))


def read_measured(path: str | os.PathLike, physics: PhysicsModel) -> MeasuredFile:
    """Read and validate a measurement file for ``physics`` (see the module docstring)."""
    path = Path(path)
    if path.suffix not in SUFFIXES:
        raise InputError(f"measured data file {str(path)!r}: unsupported suffix {path.suffix!r}, expected one of {SUFFIXES}")
    if not path.exists():
        where = (
            ""
            if path.is_absolute()
            else f", looked for at {str(path.absolute())!r}: a relative path is read from the current directory"
        )
        raise InputError(f"measured data file {str(path)!r} does not exist{where} (expected a {'/'.join(SUFFIXES)} file)")
    if not path.is_file():
        raise InputError(f"measured data file {str(path)!r} is not a file (expected a {'/'.join(SUFFIXES)} file)")
    content = _read_csv(path, physics) if path.suffix == ".csv" else {".pt": _read_pt, ".npz": _read_npz}[path.suffix](path)
    unknown = sorted(set(content) - set(KEYS) - {"ids"})
    if unknown:
        raise InputError(f"{path}: unknown entries {unknown}; a measurement file holds {list(KEYS)} (only 'y' is required)")
    if "y" not in content:
        raise InputError(f"{path}: no entry 'y' (the measured trajectories); found {sorted(content)}")
    tensors = {key: _as_tensor(path, key, value) for key, value in content.items() if key != "ids"}
    ids = content.get("ids") or [str(i) for i in range(len(tensors["y"]))]  # a CSV's own ids; else positions
    y = check_trajectories(tensors["y"], tuple(physics.obs_shape), f"{path}: 'y'")
    if "u" in tensors and not physics.input_names:
        raise InputError(f"{path}: 'u' holds recorded inputs, but {type(physics).__name__} declares none (input_names)")
    common = on_common_times(str(path), y, tensors.get("t"), ids, physics, tensors.get("u"))
    theta = _per_trajectory(path, tensors, "theta", (physics.theta_dim,), len(y), f"theta_names {tuple(physics.theta_names)}")
    x0 = _per_trajectory(path, tensors, "x0", tuple(physics.state_shape), len(y), "the model's full initial state")
    return MeasuredFile(str(path), common.y, theta, x0, common.times, common.u)


def check_trajectories(y: Tensor, obs_shape: tuple[int, ...], where: str) -> Tensor:
    """Check shape (N, T, *obs_shape) with N, T >= 1 (NaN: a missing value); return y as float32."""
    expected = "(N, T, " + ", ".join(map(str, obs_shape)) + ")"
    if y.dim() != len(obs_shape) + 2 or tuple(y.shape[2:]) != tuple(obs_shape):
        raise InputError(f"{where}: measured trajectories have shape {tuple(y.shape)}, expected {expected}")
    if len(y) == 0 or y.shape[1] == 0:
        raise InputError(f"{where}: no trajectories, expected {expected} with N, T >= 1")
    return y.float()


def _check_finite(values: Tensor, where: str, what: str) -> None:
    bad = ~torch.isfinite(values.reshape(len(values), -1)).all(dim=1)
    if bool(bad.any()):
        first = int(bad.nonzero()[0])
        raise InputError(f"{where}: NaN/Inf in {int(bad.sum())} of {len(bad)} {what}, the first at position {first} (from 0)")


def _as_tensor(path: Path, key: str, value: Any) -> Tensor:
    if isinstance(value, np.ndarray):
        if not (np.issubdtype(value.dtype, np.floating) or np.issubdtype(value.dtype, np.integer)) or value.dtype == bool:
            raise InputError(f"{path}: '{key}' has dtype {value.dtype}, expected real numbers (float or int)")
        value = torch.from_numpy(np.ascontiguousarray(value))
    if not isinstance(value, Tensor):
        raise InputError(f"{path}: '{key}' is a {type(value).__name__}, expected a tensor of real numbers")
    if value.is_complex() or value.dtype == torch.bool:
        raise InputError(f"{path}: '{key}' has dtype {value.dtype}, expected real numbers (float or int)")
    return value


def _per_trajectory(
    path: Path, tensors: dict[str, Tensor], key: str, shape: tuple[int, ...], n: int, meaning: str
) -> Tensor | None:
    if key not in tensors:
        return None
    value = tensors[key]
    if tuple(value.shape) != (n, *shape):
        expected = ", ".join(map(str, (n, *shape)))
        raise InputError(
            f"{path}: '{key}' has shape {tuple(value.shape)}, expected ({expected}): one row per trajectory, {meaning}"
        )
    _check_finite(value, f"{path}: '{key}'", "rows")
    return value.float()


def _read_pt(path: Path) -> dict[str, Any]:
    try:
        content = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # a corrupt or non-tensor file: say which and why, in one line
        raise InputError(f"{path}: cannot be read as a PyTorch file of tensors ({first_line(error)})") from None
    if isinstance(content, Tensor):
        return {"y": content}
    if not isinstance(content, dict):
        raise InputError(f"{path}: holds a {type(content).__name__}, expected a tensor or a dict of tensors with key 'y'")
    return dict(content)


def _read_npz(path: Path) -> dict[str, Any]:
    try:
        archive = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as error:
        raise InputError(f"{path}: cannot be read as an .npz archive of numeric arrays ({first_line(error)})") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: holds a single array (.npy), expected an .npz archive with named arrays ('y', ...)")
    with archive:
        try:
            return {key: archive[key] for key in archive.files}
        except ValueError as error:
            raise InputError(f"{path}: cannot be read as an .npz archive of numeric arrays ({first_line(error)})") from None


def _read_csv(path: Path, physics: PhysicsModel) -> dict[str, Any]:
    """The long layout: trajectory, t, <observed>[, <inputs>][, <theta names>][, x0_<state names>] (module docstring)."""
    if len(physics.obs_shape) != 1:
        raise InputError(
            f"{path}: CSV holds low-dimensional series; {type(physics).__name__} observes fields of shape "
            f"{tuple(physics.obs_shape)}: use a .npz or .pt file with 'y' of shape (N, *{tuple(physics.trajectory_shape)})"
        )
    observed, thetas, inputs = list(physics.observed), list(physics.theta_names), list(physics.input_names)
    initial = [f"x0_{name}" for name in physics.state_names]
    with open(path, newline="", encoding="utf-8-sig") as handle:  # -sig: a byte-order mark is not part of a name
        rows = [row for row in csv.reader(handle) if any(field.strip() for field in row)]
    if not rows:
        raise InputError(f"{path}: the file is empty, expected a header 'trajectory,t,{','.join(observed)}' and rows")
    header = [name.strip() for name in rows[0]]
    allowed = ["trajectory", "t", *observed, *inputs, *thetas, *initial]
    problems = _header_problems(header, ["trajectory", "t", *observed], allowed)
    if problems:
        raise InputError(
            f"{path}: header {header}: {problems}; expected columns 'trajectory', 't', "
            f"{observed} and optionally {inputs + thetas} and {initial}, each once"
        )
    values = _numeric_rows(path, rows[1:], len(header))
    column = {name: values[:, i] for i, name in enumerate(header)}
    for name in ("trajectory", "t"):
        if not np.isfinite(column[name]).all():
            line = int(np.flatnonzero(~np.isfinite(column[name]))[0]) + 2
            raise InputError(f"{path}, line {line}: the '{name}' column holds NaN/Inf, expected a number in every row")
    per_row = [*observed, *(name for name in inputs if name in header)]
    per_trajectory = [name for name in header[2:] if name not in per_row]
    for name in [*per_row, *per_trajectory]:
        bad = np.isinf(column[name]) if name in per_row else ~np.isfinite(column[name])
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            missing = " (an empty cell or NaN is a missing value)" if name in per_row else ""
            raise InputError(
                f"{path}, line {row + 2}: trajectory {column['trajectory'][row]:g} at t={column['t'][row]:g}: "
                f"'{name}' is {column[name][row]}, expected a finite number{missing}"
            )
    ids, starts, inverse, counts = np.unique(column["trajectory"], return_index=True, return_inverse=True, return_counts=True)
    order = np.argsort(starts)  # trajectories in the order they appear in the file
    grouped = np.split(np.argsort(inverse, kind="stable"), np.cumsum(counts)[:-1])  # each id's rows, in file order
    ids, rows = ids[order], [grouped[i] for i in order]
    steps = max(len(r) for r in rows)
    table = {name: torch.from_numpy(_padded(col, rows, steps)) for name, col in column.items()}
    content: dict[str, Any] = {"t": table["t"], "y": torch.stack([table[name] for name in observed], dim=-1)}
    content["ids"] = [f"{i:g}" for i in ids]
    recorded = [name for name in inputs if name in table]
    if recorded and recorded != inputs:
        raise InputError(
            f"{path}: columns {recorded} given without {[m for m in inputs if m not in recorded]}: give all of {inputs} or none"
        )
    if recorded:
        content["u"] = torch.stack([table[name] for name in inputs], dim=-1)
    for key, names in (("theta", thetas), ("x0", initial)):
        present = [name for name in names if name in table]
        if present and present != names:
            raise InputError(
                f"{path}: columns {present} given without {[m for m in names if m not in present]}: give all of {names} or none"
            )
        if present:
            content[key] = _constant_per_trajectory(path, table, names, ids)
    return content


def _padded(values: np.ndarray, rows: list[np.ndarray], steps: int) -> np.ndarray:
    """``values`` of each trajectory's ``rows`` as one row of (N, steps), NaN after a shorter trajectory's last."""
    out = np.full((len(rows), steps), np.nan)
    for i, index in enumerate(rows):
        out[i, : len(index)] = values[index]
    return out


def _header_problems(header: list[str], required: list[str], allowed: list[str]) -> str:
    """What is wrong with a CSV header, as a clause ("missing ['angle'], unknown ['Angle'], did you mean 'Angle' ->
    'angle'?"), or "" where nothing is."""
    missing = [name for name in required if name not in header]
    unknown = [name for name in header if name not in allowed]
    repeated = sorted({name for name in header if header.count(name) > 1})
    absent = {name.lower(): name for name in allowed if name not in header}  # a suggestion never repeats a column
    guesses = {name: difflib.get_close_matches(name.lower(), list(absent), n=1) for name in unknown}
    hints = [f"{name!r} -> {absent[guess[0]]!r}" for name, guess in guesses.items() if guess]
    parts = [f"missing {missing}"] if missing else []
    parts += [f"unknown {unknown}"] if unknown else []
    parts += [f"did you mean {', '.join(hints)}?"] if hints else []
    parts += [f"repeated {repeated}"] if repeated else []
    return ", ".join(parts)


def _numeric_rows(path: Path, rows: list[list[str]], width: int) -> np.ndarray:
    if not rows:
        raise InputError(f"{path}: a header but no rows of data")
    values = np.empty((len(rows), width))
    for line, row in enumerate(rows, start=2):
        if len(row) != width:
            raise InputError(f"{path}, line {line}: {len(row)} fields, expected {width} (as in the header)")
        try:
            values[line - 2] = [float(field) if field.strip() else np.nan for field in row]  # empty: missing
        except ValueError:
            raise InputError(f"{path}, line {line}: a field is not a number (trajectory ids are numbers too): {row}") from None
    return values


def _constant_per_trajectory(path: Path, table: dict[str, Tensor], names: list[str], ids: np.ndarray) -> Tensor:
    block = torch.stack([table[name] for name in names], dim=-1)  # (N, T, K), NaN after a shorter trajectory's last
    varying = ((block != block[:, :1]) & ~torch.isnan(block)).any(dim=(1, 2))
    if bool(varying.any()):
        raise InputError(
            f"{path}: {names} change within trajectory {ids[int(varying.nonzero()[0])]:g}; they are per-trajectory values"
        )
    return block[:, 0]
