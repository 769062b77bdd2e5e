"""Measured (target) data: generated from a known DGP and cached, or split from a user's file.

Generated sets are cached as ``<split>-<key>.pt`` where the key hashes everything they depend
on, so a changed setting regenerates them and a cached file is never overwritten with
different content. A user's file (:mod:`otgb.data.files`) is split into train / validation /
test parts that never overlap (:func:`split_indices`).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

from otgb.data.seeding import generator_for
from otgb.errors import InputError
from otgb.physics.base import PhysicsModel

CHUNK = 256


def with_measurement_noise(values: Tensor, sd: float, generator: torch.Generator) -> Tensor:
    """``values`` plus white Gaussian noise of standard deviation ``sd`` (drawn by ``generator``, on its device)."""
    if sd == 0:
        return values
    return values + sd * torch.randn(values.shape, generator=generator, device=generator.device, dtype=values.dtype)


@torch.no_grad()
def generate_measured(dgp: PhysicsModel, n: int, seed: int) -> dict[str, Tensor]:
    """|Y| = n trajectories of the DGP from its priors: y (n, T, *obs) and the inputs x0, theta (and the input signals of
    a driven DGP) they came from."""
    g = generator_for(seed, "measured")
    x0, theta, effect = dgp.sample_initial_state(n, g), dgp.sample_theta(n, g), dgp.sample_effect_params(n, g)
    signals = dgp.sample_signals(n, g)
    out = {"y": simulate_in_chunks(dgp, x0, theta, effect, signals), "x0": x0, "theta": theta}
    return out if signals is None else {**out, "signals": signals}


@torch.no_grad()
def generate_joint(physics: PhysicsModel, dgp: PhysicsModel, n: int, draws: int, seed: int, split: str) -> dict[str, Tensor]:
    """Joint samples (x0, theta, x, {y_j}): the same (x0, theta) through f_p and ``draws`` times through the DGP.

    Returns x0 (n, *state), theta (n, P), x (n, T, *obs), y (n, draws, T, *obs) and y_ref, another
    ``draws`` independent DGP draws per input (the Reference of the evaluation: DGP against DGP); a driven
    DGP's input ``signals`` (n, T_u, I) are inputs too, the same for f_p and every draw.
    """
    g = generator_for(seed, split)
    x0, theta = physics.sample_initial_state(n, g), physics.sample_theta(n, g)
    effect = dgp.sample_effect_params(n * draws, g).reshape(n, draws, -1)
    effect_ref = dgp.sample_effect_params(n * draws, g).reshape(n, draws, -1)
    signals = dgp.sample_signals(n, g)
    dgp_draws = lambda e: torch.stack([simulate_in_chunks(dgp, x0, theta, e[:, j], signals) for j in range(draws)], 1)  # noqa: E731
    out = {
        "x0": x0,
        "theta": theta,
        "x": simulate_in_chunks(physics, x0, theta, signals=signals),
        "y": dgp_draws(effect),
        "y_ref": dgp_draws(effect_ref),
    }
    return out if signals is None else {**out, "signals": signals}


def cache_key(*parts: object) -> str:
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:16]


def cached(cache_dir: str | os.PathLike, split: str, key: str, build: Callable[[], dict[str, Tensor]]) -> dict[str, Tensor]:
    """Load ``<cache_dir>/<split>-<key>.pt`` or build it and write it atomically."""
    path = Path(cache_dir) / f"{split}-{key}.pt"
    if path.is_file():
        return torch.load(path, map_location="cpu", weights_only=True)
    data = build()
    save_atomically(data, path)
    return data


def save_atomically(data: dict[str, Tensor], path: Path) -> None:
    """``torch.save`` to a temporary file beside ``path``, then renamed: a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}")
    torch.save(data, tmp)
    os.replace(tmp, path)


MIN_HELD_OUT = 10  # trajectories per held-out part: its Reference compares two halves of >= 5


def split_indices(n: int, val_fraction: float, test_fraction: float, seed: int, where: str) -> dict[str, Tensor]:
    """Disjoint random train / val / test indices of n trajectories (seeded), each part sorted.

    The held-out parts get round(fraction * n) trajectories each; the train part the rest.
    """
    for name, fraction in (("data.val_fraction", val_fraction), ("data.test_fraction", test_fraction)):
        if not 0.0 < fraction < 1.0:
            raise InputError(f"{name}={fraction}: expected a fraction in (0, 1)")
    sizes = {"val": round(val_fraction * n), "test": round(test_fraction * n)}
    sizes["train"] = n - sizes["val"] - sizes["test"]
    if min(sizes["val"], sizes["test"]) < MIN_HELD_OUT or sizes["train"] < 1:
        raise InputError(
            f"{where}: {n} trajector{'y' if n == 1 else 'ies'} split by val_fraction={val_fraction}, "
            f"test_fraction={test_fraction} give "
            f"{sizes['train']} train / {sizes['val']} validation / {sizes['test']} test; each held-out part needs >= "
            f"{MIN_HELD_OUT} and training >= 1: give more trajectories or larger fractions"
        )
    order = torch.randperm(n, generator=generator_for(seed, "measured-split"))
    parts = {"val": order[: sizes["val"]], "test": order[sizes["val"] : sizes["val"] + sizes["test"]]}
    parts["train"] = order[sizes["val"] + sizes["test"] :]
    return {name: part.sort().values for name, part in parts.items()}


@torch.no_grad()
def simulate_in_chunks(
    model: PhysicsModel, x0: Tensor, theta: Tensor, effect: Tensor | None = None, signals: Tensor | None = None
) -> Tensor:
    """Trajectories (n, T, *obs) of ``model`` for the inputs x0 (n, *state), theta (n, P) [, effect parameters and
    input signals (n, T_u, I)]."""
    chunks = range(0, len(x0), CHUNK)
    part = lambda v, i: None if v is None else v[i : i + CHUNK]  # noqa: E731
    return torch.cat(
        [_simulate_rows(model, i, x0[i : i + CHUNK], theta[i : i + CHUNK], part(effect, i), part(signals, i)) for i in chunks]
    )


def _simulate_rows(
    model: PhysicsModel, first: int, x0: Tensor, theta: Tensor, effect: Tensor | None, signals: Tensor | None
) -> Tensor:  # fmt: skip
    with model.rows_from(first):
        return model.simulate(x0, theta, effect, signals)
