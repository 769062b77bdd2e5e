"""What the discovery can add when the data-generating process is known (a config's hidden effect).

``otgb discover`` on a joint config (``data.hidden_effect`` set, no file) generates the
measurements from the DGP as ``otgb fit`` does; the workflow itself sees only the generated
trajectories. Knowing the DGP then also gives pointwise errors on the test inputs (ABS ERR and
N-RMSE of f_p, the grey-box and the augmented physics against the DGP's draws for the same
inputs) and how each extrapolates to twice the time horizon.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

import torch
from torch import Tensor

from otgb.discovery.log import diverged
from otgb.metrics.errors import abs_err, nrmse
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel, SimulationDiverged


@contextmanager
def horizon(physics: PhysicsModel, n_obs: int) -> Iterator[None]:
    """Solve ``physics`` (and any model or map that solves with it) over ``n_obs`` observations for a while."""
    saved = physics.n_obs
    physics.n_obs = n_obs
    try:
        yield
    finally:
        physics.n_obs = saved


@torch.no_grad()
def pointwise_errors(module: Any, dgp: PhysicsModel, augmented: Augmented | None, test: dict[str, Tensor], seed: int) -> dict:
    """ABS ERR and N-RMSE against the DGP on the test inputs, over the training horizon and twice it."""
    physics = module.physics
    n_obs = physics.n_obs
    x0, theta = test["x0"], test["theta"]
    g = torch.Generator().manual_seed(seed)
    out: dict[str, dict[str, float]] = {}
    with horizon(dgp, 2 * n_obs):
        signals = held_to(test.get("signals"), dgp)  # beyond the training horizon, each input holds its last value
        truth = dgp.simulate(x0, theta, dgp.sample_effect_params(len(x0), g) if dgp.effect_dim else None, signals)
    sources = {
        "f_p": lambda: physics.simulate(x0, theta, signals=signals),
        "greybox": lambda: _greybox(module, x0, theta, signals),
    }
    if augmented is not None:
        coefficients = augmented.sample_theta(len(x0), g)[:, physics.theta_dim :]
        sources["augmented"] = lambda: augmented.simulate(x0, torch.cat([theta, coefficients], 1), signals=signals)
    models = {physics, module.evaluation_map().physics, *([augmented] if augmented is not None else [])}
    with ExitStack() as stack:
        for model in models:
            stack.enter_context(horizon(model, 2 * n_obs))
        for name, simulate in sources.items():
            try:
                out[name] = _errors(simulate(), truth, n_obs)
            except SimulationDiverged as error:  # a named term that blows up beyond the training horizon
                diverged(f"pointwise errors ({name}, twice the horizon)", [str(error)], len(x0), len(x0), None)
    return out


def _greybox(module: Any, x0: Tensor, theta: Tensor, signals: Tensor | None) -> Tensor:
    rng = module.generator.get_state()
    z = module.sample_z(len(x0))
    module.generator.set_state(rng)
    transport_map = module.evaluation_map()
    signals = None if signals is None else signals.to(module.device)
    return transport_map(None, x0.to(module.device), theta.to(module.device), z, signals=signals).cpu()


def held_to(signals: Tensor | None, model: PhysicsModel) -> Tensor | None:
    """Input signals (n, T_u, I) extended to ``model``'s signal times, each holding its last value after its own."""
    if signals is None:
        return None
    extra = len(model.signal_times()) - signals.shape[1]
    return torch.cat([signals, signals[:, -1:].expand(-1, max(extra, 0), -1)], dim=1)


def _errors(prediction: Tensor, truth: Tensor, n_obs: int) -> dict[str, float]:
    value_range = truth[:, :n_obs].max() - truth[:, :n_obs].min()
    parts = {"horizon": slice(0, n_obs), "twice_horizon": slice(n_obs, 2 * n_obs)}
    out = {}
    for label, part in parts.items():
        out[f"abs_err_{label}"] = float(abs_err(prediction[:, part], truth[:, part]).mean())
        out[f"nrmse_{label}"] = float(nrmse(prediction[:, part], truth[:, part], value_range).mean())
    return out
