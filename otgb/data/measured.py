"""Measured (target) data and joint evaluation sets: generate, cache, load, validate.

Files on disk
-------------
A user's measured set is a ``.pt`` file (a tensor, or a dict with key ``"y"``) or an
``.npz`` file with key ``"y"``; ``y`` has shape (N, T, *obs_shape), e.g. (N, 50, 1) for the
pendulum, and must be finite. Generated sets are cached as ``<split>-<key>.pt`` where the
key hashes everything they depend on, so a changed setting regenerates them and a cached
file is never overwritten with different content.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from otgb.data.seeding import generator_for
from otgb.physics.base import PhysicsModel

CHUNK = 256


def check_trajectories(y: Tensor, trajectory_shape: tuple[int, ...], where: str) -> Tensor:
    """Check shape (N, *trajectory_shape) and finiteness; return y as float32."""
    expected = "(N, " + ", ".join(map(str, trajectory_shape)) + ")"
    if y.dim() != len(trajectory_shape) + 1 or tuple(y.shape[1:]) != tuple(trajectory_shape):
        raise ValueError(f"{where}: measured trajectories have shape {tuple(y.shape)}, expected {expected}")
    if len(y) == 0:
        raise ValueError(f"{where}: the measured set is empty, expected {expected} with N >= 1")
    bad = ~torch.isfinite(y.flatten(1)).all(dim=1)
    if bool(bad.any()):
        raise ValueError(
            f"{where}: {int(bad.sum())} measured trajectories contain NaN/Inf (first at index {int(bad.nonzero()[0])})"
        )
    return y.float()


def load_measured(path: str | os.PathLike, trajectory_shape: tuple[int, ...]) -> Tensor:
    """Load a user's measured set from .pt or .npz (key ``"y"``), validated."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"measured data file {str(path)!r} does not exist (expected a .pt or .npz file with key 'y')")
    if path.suffix == ".npz":
        with np.load(path) as archive:
            if "y" not in archive:
                raise KeyError(f"{path}: no array 'y' in the .npz file (found {sorted(archive.files)})")
            y = torch.from_numpy(archive["y"])
    elif path.suffix == ".pt":
        content = torch.load(path, map_location="cpu", weights_only=True)
        if isinstance(content, dict):
            if "y" not in content:
                raise KeyError(f"{path}: no tensor 'y' in the .pt dict (found {sorted(content)})")
            content = content["y"]
        if not isinstance(content, Tensor):
            raise TypeError(f"{path}: expected a tensor or a dict with tensor 'y', got {type(content).__name__}")
        y = content
    else:
        raise ValueError(f"measured data file {str(path)!r}: unsupported suffix {path.suffix!r}, expected .pt or .npz")
    return check_trajectories(y, trajectory_shape, str(path))


@torch.no_grad()
def generate_measured(dgp: PhysicsModel, n: int, seed: int) -> Tensor:
    """|Y| = n trajectories of the DGP from its priors, (n, T, *obs)."""
    g = generator_for(seed, "measured")
    x0, theta, effect = dgp.sample_initial_state(n, g), dgp.sample_theta(n, g), dgp.sample_effect_params(n, g)
    return torch.cat([dgp.simulate(x0[i : i + CHUNK], theta[i : i + CHUNK], effect[i : i + CHUNK]) for i in range(0, n, CHUNK)])


@torch.no_grad()
def generate_joint(physics: PhysicsModel, dgp: PhysicsModel, n: int, draws: int, seed: int, split: str) -> dict[str, Tensor]:
    """Joint samples (x0, theta, x, {y_j}): the same (x0, theta) through f_p and ``draws`` times through the DGP.

    Returns x0 (n, *state), theta (n, P), x (n, T, *obs), y (n, draws, T, *obs) and y_ref, another
    ``draws`` independent DGP draws per input (the Reference of the evaluation: DGP against DGP).
    """
    g = generator_for(seed, split)
    x0, theta = physics.sample_initial_state(n, g), physics.sample_theta(n, g)
    effect = dgp.sample_effect_params(n * draws, g).reshape(n, draws, -1)
    effect_ref = dgp.sample_effect_params(n * draws, g).reshape(n, draws, -1)
    x, y, y_ref = [], [], []
    for i in range(0, n, CHUNK):
        s = slice(i, i + CHUNK)
        x.append(physics.simulate(x0[s], theta[s]))
        y.append(torch.stack([dgp.simulate(x0[s], theta[s], effect[s, j]) for j in range(draws)], dim=1))
        y_ref.append(torch.stack([dgp.simulate(x0[s], theta[s], effect_ref[s, j]) for j in range(draws)], dim=1))
    return {"x0": x0, "theta": theta, "x": torch.cat(x), "y": torch.cat(y), "y_ref": torch.cat(y_ref)}


def cache_key(*parts: object) -> str:
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:16]


def cached(cache_dir: str | os.PathLike, split: str, key: str, build: Callable[[], dict[str, Tensor]]) -> dict[str, Tensor]:
    """Load ``<cache_dir>/<split>-<key>.pt`` or build it and write it atomically."""
    path = Path(cache_dir) / f"{split}-{key}.pt"
    if path.is_file():
        return torch.load(path, map_location="cpu", weights_only=True)
    data = build()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}")
    torch.save(data, tmp)
    os.replace(tmp, path)
    return data
