"""Trajectories drawn for discovery: f_p's and a candidate model's from their priors, the grey-box's with its
components, and random subsets of measured rows; each stream from :class:`~otgb.discovery.seeds.Seeds`."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from otgb.data.measured import CHUNK, simulate_in_chunks
from otgb.discovery.log import diverged
from otgb.discovery.scores import simulate_finite, term_names
from otgb.discovery.seeds import Seeds
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel


@torch.no_grad()
def simulate_from_priors(physics: PhysicsModel, n: int, seeds: Seeds, name: str) -> Tensor:
    """n observed trajectories of ``physics`` with inputs from its priors drawn from the stream ``name``, (n, T, *obs)."""
    g = seeds.simulation(name)
    x0, theta = physics.sample_initial_state(n, g), physics.sample_theta(n, g)
    return simulate_in_chunks(physics, x0, theta, signals=physics.sample_signals(n, g))


@torch.no_grad()
def simulate_candidate(model: Augmented, n: int, seeds: Seeds, name: str) -> Tensor:
    """:func:`simulate_from_priors` for a candidate model: the trajectories that diverge are dropped and logged."""
    g = seeds.simulation(name)
    x0, theta, signals = model.sample_initial_state(n, g), model.sample_theta(n, g), model.sample_signals(n, g)
    rows = lambda v, i: None if v is None else v[i : i + CHUNK]  # noqa: E731
    kept, bad = zip(
        *(_simulate_finite_rows(model, i, x0[i : i + CHUNK], theta[i : i + CHUNK], rows(signals, i)) for i in range(0, n, CHUNK))
    )
    bad = torch.cat(bad)
    if bool(bad.any()):
        first, coefficients = theta[int(bad.nonzero()[0])].tolist(), [repr(t.priors["coefficient"]) for t in model.added]
        diverged(name, term_names(model.added), int(bad.sum()), n, first, coefficients)
    return torch.cat(kept)


def _simulate_finite_rows(
    model: Augmented, first: int, x0: Tensor, theta: Tensor, signals: Tensor | None
) -> tuple[Tensor, Tensor]:  # fmt: skip
    with model.rows_from(first):
        return simulate_finite(model, x0, theta, signals)


GREYBOX = "greybox"  # the grey-box's stream of inputs; f_p simulated from it gets the same (x0, theta)


@torch.no_grad()
def greybox_draws(module: Any, n: int, seeds: Seeds) -> dict[str, Tensor]:
    """The grey-box's states, f_p and f_phi (in state space) along n generated trajectories from the priors (and, for a
    driven model, the inputs along them)."""
    physics = module.physics
    g = seeds.simulation(GREYBOX)
    x0, theta, signals = physics.sample_initial_state(n, g), physics.sample_theta(n, g), physics.sample_signals(n, g)
    transport_map, device = module.evaluation_map(), module.device
    rng = module.generator.get_state()
    parts = []
    for i in range(0, n, CHUNK):
        z = module.sample_z(len(x0[i : i + CHUNK]))
        rows = None if signals is None else signals[i : i + CHUNK].to(device)
        parts.append(transport_map.components(x0[i : i + CHUNK].to(device), theta[i : i + CHUNK].to(device), z, rows))
    module.generator.set_state(rng)
    out = {key: torch.cat([p[key] for p in parts]).cpu() for key in parts[0]}
    flat = out["correction"].flatten(0, 1)
    out["correction"] = physics.add_correction(torch.zeros_like(out["states"].flatten(0, 1)), flat).reshape(out["states"].shape)
    out["observed"] = physics.observe(out["states"])
    out["theta"] = theta
    return out


def acting_components(physics: PhysicsModel) -> list[str]:
    """The state components the grey-box's correction can change."""
    probe = torch.zeros(1, *physics.state_shape)
    reach = physics.add_correction(probe, torch.ones(1, *physics.correction_shape)).reshape(len(physics.state_names), -1)
    reach = reach.abs().sum(-1)
    return [name for name, r in zip(physics.state_names, reach) if r > 0]


def at_most(rows: Tensor, n: int, seeds: Seeds) -> Tensor:
    """``rows``, or ``n`` of them drawn at random (in their order) where there are more. One permutation per number of
    rows, whatever the model compared with them: the before and after maps of a part see the same trajectories, and a
    smaller subset of a part is a part of a larger one."""
    if len(rows) <= n:
        return rows
    drawn = torch.randperm(len(rows), generator=seeds.rows(len(rows)))
    return rows[drawn[:n].sort().values]


@torch.no_grad()
def generated(module: Any, n: int, seeds: Seeds) -> Tensor:
    """n trajectories of the grey-box with inputs from the priors, (n, T, *obs)."""
    return greybox_draws(module, n, seeds)["observed"][:, -module.physics.n_obs :]
