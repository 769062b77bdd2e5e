"""Component analysis of the grey-box: what f_p and f_phi each do along the generated solve.

The paper ("Hybrid Generative Modeling for Incomplete Physics: Deep Grey-Box Meets Optimal
Transport", Discussion, "Inspecting inside the Grey-Box: Component Analysis" and its Figure 3)
inspects the trained map dy/dt = f_p(y, theta) + f_phi(y, theta, z) at three levels:

- trajectory level: the generated observed trajectories against the measured ones;
- function level: f_p + f_phi against the true vector field, at the states of the grey-box's
  own solve ("in-solver function evaluation errors"), next to f_p alone;
- the learned component over time: |f_phi| and |f_p| along the solve.

:func:`component_analysis` computes them for a model and a data module (the discovery
workflow calls it as well); :class:`ComponentAnalysis` runs it at the end of ``otgb fit`` and
writes ``components.json`` and ``figures/components.png`` into the run's log directory.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from lightning import Callback, LightningModule, Trainer  # noqa: E402
from lightning.pytorch.loggers import TensorBoardLogger  # noqa: E402
from lightning.pytorch.utilities import rank_zero_warn  # noqa: E402
from torch import Tensor  # noqa: E402

from otgb.data import SimulationDataModule  # noqa: E402
from otgb.errors import InputError  # noqa: E402
from otgb.metrics.energy import energy_per_time  # noqa: E402
from otgb.physics.base import PhysicsModel  # noqa: E402
from otgb.training import MapTraining  # noqa: E402


def per_time(values: Tensor) -> Tensor:
    """Mean absolute value per time step: (B, T, ...) -> (T,)."""
    return values.abs().transpose(0, 1).flatten(1).mean(1)


def solve_components(model: MapTraining, x0: Tensor, theta: Tensor, seed: int) -> dict[str, Tensor]:
    """The evaluation map's components along its solve for x0 (B, *state), theta (B, P), on the CPU.

    z comes from ``model.sample_z`` with ``model.generator`` seeded by ``seed`` for the draw
    and put back afterwards, so training's draws do not move. Returns ``states``, ``physics``
    (f_p) and ``correction`` (f_phi put into state space by ``physics.add_correction``), each
    (B, T, *state).
    """
    transport_map = model.evaluation_map()
    rng = model.generator.get_state()
    try:
        model.generator.manual_seed(seed)
        z = model.sample_z(len(x0))
    finally:
        model.generator.set_state(rng)
    parts = transport_map.components(x0.to(model.device), theta.to(model.device), z)
    parts = {k: v.cpu() for k, v in parts.items()}
    f_p, physics = parts["physics"], transport_map.physics
    correction = physics.add_correction(torch.zeros_like(f_p.flatten(0, 1)), parts["correction"].flatten(0, 1))
    return {"states": parts["states"], "physics": f_p, "correction": correction.reshape(f_p.shape)}


def trajectory_error(y_hat: Tensor, y: Tensor, datamodule: SimulationDataModule) -> tuple[Tensor, str]:
    """Error per time step (T,) of the generated y_hat against the measured y, both (n, M, T, *obs).

    A deterministic DGP pairs each draw with the DGP's draw for the same inputs: ABS ERR,
    mean |y_hat - y| over inputs, draws and observed components. A stochastic DGP or a
    measured file has no pointwise counterpart: the energy distance between the two samples
    at each time step (:func:`otgb.metrics.energy.energy_per_time`), averaged over components,
    paired where both sides share recorded inputs.
    """
    if datamodule.mode == "joint" and not datamodule.dgp.is_stochastic:
        return per_time(y_hat.flatten(0, 1) - y.flatten(0, 1)), "abs_err"
    rows = lambda v: v.flatten(0, 1).flatten(1)  # noqa: E731
    paired = bool(datamodule.recorded_inputs)
    return energy_per_time(rows(y_hat), rows(y), tuple(y.shape[2:]), paired).mean(1), "energy"


def true_field(dgp: PhysicsModel | None, states: Tensor, theta: Tensor, seed: int) -> tuple[Tensor | None, str | None]:
    """The DGP's vector field at states (B, T, *state) for theta (B, P), or None and why not.

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
    field = dgp.vector_field(states.flatten(0, 1), theta.repeat_interleave(steps, dim=0), effect)
    return field.reshape(states.shape), None


@torch.no_grad()
def component_analysis(model: MapTraining, datamodule: SimulationDataModule, n: int = 64, seed: int = 0) -> dict[str, Any]:
    """The paper's component analysis (Figure 3) on the first ``n`` validation inputs.

    The model's evaluation map (the moving average of its weights when there is one) must
    have ``components`` (:class:`otgb.models.GreyBoxODE`); the data module must be set up. Each input is
    solved once per measured draw (M of them), with z drawn from ``model.sample_z`` under ``seed``.

    Returns, per time step (T,) unless said otherwise:

    - ``traj_err`` and ``traj_err_kind``: see :func:`trajectory_error` ("abs_err" or "energy");
    - ``func_err``: mean |f_p + f_phi - f_true| over trajectories and state components, and
      ``func_err_fp``: mean |f_p - f_true|; both None when there is no true field, with the
      reason in ``func_err_unavailable`` (see :func:`true_field`);
    - ``f_p_abs``, ``f_phi_abs``: mean |f_p| and |f_phi| over trajectories and state components,
      and ``correction_share``: f_phi_abs / (f_p_abs + f_phi_abs), in [0, 1];
    - ``times`` (T,), ``mode``, ``n_inputs``, ``draws_per_input``, and ``summary``: the floats
      ``traj_err``, ``func_err``, ``func_err_fp`` (time means; None if unavailable) and
      ``correction_share`` (of the time means).
    """
    if not hasattr(model.evaluation_map(), "components"):
        raise TypeError(f"component_analysis needs a grey-box map with components(), got {type(model.evaluation_map()).__name__}")
    data = {k: v[:n] for k, v in datamodule.val_set.items()}
    if len(data["y"]) < 2:
        raise ValueError(f"component_analysis needs at least 2 validation inputs, got {len(data['y'])}")
    draws = data["y"].shape[1]
    theta = data["theta"].repeat_interleave(draws, dim=0)
    parts = solve_components(model, data["x0"].repeat_interleave(draws, dim=0), theta, seed)
    y_hat = datamodule.physics.observe(parts["states"]).reshape(data["y"].shape)
    traj_err, kind = trajectory_error(y_hat, data["y"], datamodule)
    truth, unavailable = true_field(datamodule.dgp, parts["states"], theta, seed)
    f_p, f_phi = parts["physics"], parts["correction"]
    func_err = None if truth is None else per_time(f_p + f_phi - truth)
    func_err_fp = None if truth is None else per_time(f_p - truth)
    f_p_abs, f_phi_abs = per_time(f_p), per_time(f_phi)
    mean = lambda v: None if v is None else float(v.mean())  # noqa: E731
    return {
        "mode": datamodule.mode,
        "n_inputs": len(data["y"]),
        "draws_per_input": draws,
        "times": datamodule.physics.observation_times(),
        "traj_err": traj_err,
        "traj_err_kind": kind,
        "func_err": func_err,
        "func_err_fp": func_err_fp,
        "func_err_unavailable": unavailable,
        "f_p_abs": f_p_abs,
        "f_phi_abs": f_phi_abs,
        "correction_share": f_phi_abs / (f_p_abs + f_phi_abs),
        "summary": {
            "traj_err": mean(traj_err),
            "func_err": mean(func_err),
            "func_err_fp": mean(func_err_fp),
            "correction_share": float(f_phi_abs.mean() / (f_p_abs.mean() + f_phi_abs.mean())),
        },
    }


def to_json(result: dict[str, Any]) -> dict[str, Any]:
    """The analysis with its tensors as lists (None stays None)."""
    return {k: to_json(v) if isinstance(v, dict) else v.tolist() if isinstance(v, Tensor) else v for k, v in result.items()}


def components_figure(result: dict[str, Any]) -> plt.Figure:
    """Three panels over time: trajectory-level error, function-level errors, |f_p| and |f_phi|."""
    t = result["times"].numpy()
    figure, (traj, func, parts) = plt.subplots(1, 3, figsize=(13, 3.4))
    traj.plot(t, result["traj_err"].numpy(), color="tab:green")
    traj.set_title(f"trajectory level ({'ABS ERR' if result['traj_err_kind'] == 'abs_err' else 'energy distance'})", fontsize=9)
    if result["func_err"] is None:
        reason = textwrap.fill(f"not available: {result['func_err_unavailable']}", 40)
        func.text(0.5, 0.5, reason, ha="center", va="center", fontsize=8)
        func.set_xticks([])
        func.set_yticks([])
    else:
        func.plot(t, result["func_err_fp"].numpy(), color="tab:orange", ls="--", label="f_p")
        func.plot(t, result["func_err"].numpy(), color="tab:green", label="f_p + f_phi")
        func.legend(fontsize=7)
    func.set_title("function level: mean |f - f_true|", fontsize=9)
    parts.plot(t, result["f_p_abs"].numpy(), color="tab:orange", ls="--", label="|f_p|")
    parts.plot(t, result["f_phi_abs"].numpy(), color="tab:green", label="|f_phi|")
    parts.set_title(f"components along the solve (f_phi share {result['summary']['correction_share']:.3g})", fontsize=9)
    parts.legend(fontsize=7)
    for ax in (traj, func, parts):
        ax.set_xlabel("t", fontsize=8)
    figure.tight_layout()
    return figure


class ComponentAnalysis(Callback):
    """Runs :func:`component_analysis` once, when ``otgb fit`` ends its training (rank 0 only).

    Writes ``<log_dir>/components.json`` (:func:`component_analysis`'s result) and
    ``<log_dir>/figures/components.png``, adds the figure to TensorBoard and logs
    ``components/<name>`` for each summary float (``traj_err``, ``func_err``, ``func_err_fp``,
    ``correction_share``; the function-level ones only where available) to every logger. It
    runs at ``on_train_end``, while the module is still on its training device (Lightning
    moves it to the CPU before ``on_fit_end``). A map without components (not a grey-box) is
    skipped with a warning.

    Args:
        n: Validation inputs analysed (the first ones of the validation set); at least 2.
        seed: Seed of the analysis' latent draws z.
        enabled: Whether to run the analysis at the end of training.
    """

    def __init__(self, n: int = 64, seed: int = 0, enabled: bool = True) -> None:
        if n < 2:
            raise InputError(f"components.n={n}: expected >= 2 validation inputs")
        self.n, self.seed, self.enabled = n, seed, enabled

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        log_dir = trainer.log_dir  # a collective call under DDP: every process makes it
        if not self.enabled or not trainer.is_global_zero:
            return
        if not hasattr(pl_module.evaluation_map(), "components"):
            rank_zero_warn(f"ComponentAnalysis: {type(pl_module.evaluation_map()).__name__} has no components(); skipped")
            return
        result = component_analysis(pl_module, trainer.datamodule, self.n, self.seed)
        scalars = {f"components/{k}": v for k, v in result["summary"].items() if v is not None}
        figure = components_figure(result)
        for logger in trainer.loggers:
            logger.log_metrics(scalars, step=trainer.global_step)
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_figure("components", figure, global_step=trainer.global_step, close=False)
        if log_dir is not None:
            out = Path(log_dir)
            (out / "figures").mkdir(parents=True, exist_ok=True)
            (out / "components.json").write_text(json.dumps(to_json(result), indent=1))
            figure.savefig(out / "figures" / "components.png", dpi=80)
        plt.close(figure)
