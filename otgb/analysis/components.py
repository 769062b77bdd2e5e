"""Component analysis of the grey-box: what f_p and f_phi each do along the generated solve.

The paper ("Hybrid Generative Modeling for Incomplete Physics: Deep Grey-Box Meets Optimal
Transport", Discussion, "Inspecting inside the Grey-Box: Component Analysis" and its Figure 3)
inspects the trained map dy/dt = f_p(y, theta) + f_phi(y, theta, z) at three levels:

- trajectory level: the generated observed trajectories against the measured ones;
- function level: f_p + f_phi against the true vector field, at the states of the grey-box's
  own solve ("in-solver function evaluation errors"), next to f_p alone;
- the learned component over time: |f_phi| and |f_p| along the solve.

:func:`component_analysis` computes them for a model and a data module; the callback
:class:`otgb.callbacks.ComponentAnalysis` runs it at the end of ``otgb fit`` and ``otgb discover``
calls it too. :func:`otgb.analysis.figures.components_figure` draws them.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from otgb.data import SimulationDataModule
from otgb.data.measured import simulate_in_chunks
from otgb.metrics.energy import energy_per_time
from otgb.physics.base import PhysicsModel
from otgb.training import MapTraining


def per_time(values: Tensor) -> Tensor:
    """Mean absolute value per time step: (B, T, ...) -> (T,)."""
    return values.abs().transpose(0, 1).flatten(1).mean(1)


def solve_components(
    model: MapTraining, x0: Tensor, theta: Tensor, seed: int, signals: Tensor | None = None
) -> dict[str, Tensor]:
    """The evaluation map's components along its solve for x0 (B, *state), theta (B, P) [and the input signals of a
    driven model], on the CPU.

    z comes from ``model.sample_z`` with ``model.generator`` seeded by ``seed`` for the draw
    and put back afterwards, so training's draws do not move. Returns ``states``, ``physics``
    (f_p) and ``correction`` (f_phi put into state space by ``physics.add_correction``), each
    (B, T, *state), and a driven model's ``inputs`` (B, T, I) along them.
    """
    transport_map = model.evaluation_map()
    rng = model.generator.get_state()
    try:
        model.generator.manual_seed(seed)
        z = model.sample_z(len(x0))
    finally:
        model.generator.set_state(rng)
    signals = None if signals is None else signals.to(model.device)
    parts = transport_map.components(x0.to(model.device), theta.to(model.device), z, signals)
    parts = {k: v.cpu() for k, v in parts.items()}
    f_p, physics = parts["physics"], transport_map.physics
    correction = physics.add_correction(torch.zeros_like(f_p.flatten(0, 1)), parts["correction"].flatten(0, 1))
    out = {"states": parts["states"], "physics": f_p, "correction": correction.reshape(f_p.shape)}
    return out if "inputs" not in parts else {**out, "inputs": parts["inputs"]}


def trajectory_error(y_hat: Tensor, y: Tensor, datamodule: SimulationDataModule) -> tuple[Tensor, str]:
    """Error per time step (T,) of the generated y_hat against the measured y, both (n, M, T, *obs).

    A deterministic DGP pairs each draw with the DGP's draw for the same inputs: ABS ERR,
    mean |y_hat - y| over inputs, draws and observed components. A stochastic DGP or a
    measured file has no pointwise counterpart: the energy distance between the two samples
    at each time step (:func:`otgb.metrics.energy.energy_per_time`), averaged over components,
    paired where both sides share recorded inputs; over the trajectories measured at that step
    (NaN where fewer than 2 are).
    """
    if datamodule.source.pointwise_process is not None:
        return per_time(y_hat.flatten(0, 1) - y.flatten(0, 1)), "abs_err"  # generated measurements: never missing
    rows = lambda v: v.flatten(0, 1).flatten(1)  # noqa: E731
    paired = bool(datamodule.recorded_inputs)
    return energy_per_time(rows(y_hat), rows(y), tuple(y.shape[2:]), paired).mean(1), "energy"


def true_field(
    dgp: PhysicsModel | None, states: Tensor, theta: Tensor, seed: int, inputs: Tensor | None = None
) -> tuple[Tensor | None, str | None]:
    """The DGP's vector field at states (B, T, *state) for theta (B, P) [and inputs (B, T, I)], or None and why not.

    It exists only in the joint mode with a deterministic DGP: a measured file has no known
    field, and a DGP whose hidden-effect parameters are random (one-to-many, e.g. the friction
    xi drawn per trajectory) does not say which value made a given trajectory, nor does the
    map's z name it, so along one generated trajectory there is no true field to compare with.
    """
    if dgp is None:
        return None, "no data-generating process: the measurements come from a file"
    if dgp.is_stochastic:
        return None, "the hidden effect's parameters are random: the true field of a trajectory is not identified"
    steps = states.shape[1]
    effect = dgp.sample_effect_params(len(states) * steps, torch.Generator().manual_seed(seed))
    flat_inputs = None if inputs is None else inputs.flatten(0, 1)
    field = dgp.vector_field(states.flatten(0, 1), theta.repeat_interleave(steps, dim=0), effect, flat_inputs)
    return field.reshape(states.shape), None


@torch.no_grad()
def component_analysis(model: MapTraining, datamodule: SimulationDataModule, n: int = 64, seed: int = 0) -> dict[str, Any]:
    """The paper's component analysis (Figure 3) on the first ``n`` validation inputs.

    The model's evaluation map (the moving average of its weights when there is one) must
    have ``components`` (:class:`otgb.models.GreyBoxODE`); the data module must be set up. Each input is
    solved once per measured draw (M of them), with z drawn from ``model.sample_z`` under ``seed``.

    Returns, per time step (T,) unless said otherwise:

    - ``traj_err`` and ``traj_err_kind``: see :func:`trajectory_error` ("abs_err" or "energy"), and
      ``traj_err_fp``: the same for f_p alone solved from the same inputs;
    - ``func_err``: mean |f_p + f_phi - f_true| over trajectories and state components, and
      ``func_err_fp``: mean |f_p - f_true|; both None when there is no true field, with the
      reason in ``func_err_unavailable`` (see :func:`true_field`);
    - ``f_p_abs``, ``f_phi_abs``: mean |f_p| and |f_phi| over trajectories and state components,
      and ``correction_share``: f_phi_abs / (f_p_abs + f_phi_abs), in [0, 1];
    - ``times`` (T,), ``time_label`` (the time axis's label, with its unit where the physics declares one),
      ``mode``, ``n_inputs``, ``draws_per_input``, and ``summary``: the floats
      ``traj_err``, ``func_err``, ``func_err_fp`` (time means; None if unavailable) and
      ``correction_share`` (of the time means).
    """
    if not hasattr(model.evaluation_map(), "components"):
        raise TypeError(f"component_analysis needs a grey-box map with components(), got {type(model.evaluation_map()).__name__}")
    data = {k: v[:n] for k, v in datamodule.val_set.items()}
    if len(data["y"]) < 2:
        raise ValueError(f"component_analysis needs at least 2 validation inputs, got {len(data['y'])}")
    draws = data["y"].shape[1]
    x0, theta = data["x0"].repeat_interleave(draws, dim=0), data["theta"].repeat_interleave(draws, dim=0)
    signals = data["signals"].repeat_interleave(draws, dim=0) if "signals" in data else None
    parts = solve_components(model, x0, theta, seed, signals)
    y_hat = datamodule.physics.observe(parts["states"]).reshape(data["y"].shape)
    traj_err, kind = trajectory_error(y_hat, data["y"], datamodule)
    physics = model.evaluation_map().physics
    on_device = None if signals is None else signals.to(model.device)
    y_fp = (
        simulate_in_chunks(physics, x0.to(model.device), theta.to(model.device), signals=on_device).cpu().reshape(data["y"].shape)
    )
    traj_err_fp, _ = trajectory_error(y_fp, data["y"], datamodule)
    truth, unavailable = true_field(datamodule.dgp, parts["states"], theta, seed, parts.get("inputs"))
    f_p, f_phi = parts["physics"], parts["correction"]
    func_err = None if truth is None else per_time(f_p + f_phi - truth)
    func_err_fp = None if truth is None else per_time(f_p - truth)
    f_p_abs, f_phi_abs = per_time(f_p), per_time(f_phi)
    mean = lambda v: None if v is None else float(v.nanmean())  # noqa: E731 (NaN: a time too few measured it)
    return {
        "mode": datamodule.mode,
        "n_inputs": len(data["y"]),
        "draws_per_input": draws,
        "times": datamodule.physics.observation_times(),
        "time_label": datamodule.physics.axis_label("t"),
        "traj_err": traj_err,
        "traj_err_fp": traj_err_fp,
        "traj_err_kind": kind,
        "func_err": func_err,
        "func_err_fp": func_err_fp,
        "func_err_unavailable": unavailable,
        "f_p_abs": f_p_abs,
        "f_phi_abs": f_phi_abs,
        "correction_share": f_phi_abs / (f_p_abs + f_phi_abs),
        "summary": {
            "traj_err": mean(traj_err),
            "traj_err_fp": mean(traj_err_fp),
            "func_err": mean(func_err),
            "func_err_fp": mean(func_err_fp),
            "correction_share": float(f_phi_abs.mean() / (f_p_abs.mean() + f_phi_abs.mean())),
        },
    }


def to_json(result: dict[str, Any]) -> dict[str, Any]:
    """The analysis with its tensors as lists (None stays None)."""
    return {k: to_json(v) if isinstance(v, dict) else v.tolist() if isinstance(v, Tensor) else v for k, v in result.items()}
