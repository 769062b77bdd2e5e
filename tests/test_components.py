"""The grey-box's component analysis (the paper's Figure 3): through `otgb fit`, by hand, on a measured file."""

import json
import math
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from otgb.analysis.components import component_analysis
from otgb.cli import main
from otgb.command import logger_override
from otgb.data import SimulationDataModule
from otgb.models import ConditionalMLP, GreyBoxODE, MLPCritic
from otgb.physics import Constant, Pendulum, Uniform, ViscousFriction
from otgb.training import MapTraining

ROOT = Path(__file__).parents[1]
CONFIG = str(ROOT / "configs" / "pendulum.yaml")


class Friction(nn.Module):
    """f_phi that is exactly the DGP's hidden term: -1.2 * velocity on the acceleration."""

    def forward(self, state: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        return -1.2 * state[:, 1:2]


def _model(correction, z_dim: int = 0, ema_decay: float | None = None) -> MapTraining:
    return MapTraining(
        Pendulum(),
        lambda physics, z: GreyBoxODE(physics, z, correction),
        partial(MLPCritic, hidden=[8]),
        z_dim=z_dim,
        ema_decay=ema_decay,
    )


def _data(tmp_path: Path, xi=None, **kw) -> SimulationDataModule:
    effect = [ViscousFriction(xi or Constant(1.2))]
    datamodule = SimulationDataModule(Pendulum(), hidden_effect=effect, n_val=6, cache_dir=str(tmp_path), **kw)
    datamodule.setup("validate")
    return datamodule


def test_fit_writes_the_analysis(tmp_path):
    args = ["--config", CONFIG, logger_override(str(tmp_path), "run"), "--trainer.enable_progress_bar=false"]
    args += ["--trainer.max_steps=4", "--trainer.val_check_interval=2", "--data.simulation_budget=3200"]
    args += ["--data.batch_size=8", "--data.n_measured=32", "--data.n_val=12", f"--data.cache_dir={tmp_path / 'cache'}"]
    args += ["--evaluation.tests_every=0", "--evaluation.reference_repeats=1", "--components.n=10"]
    main(["fit", *args])
    run = tmp_path / "run" / "version_0"
    result = json.loads((run / "components.json").read_text())
    assert result["mode"] == "joint" and result["traj_err_kind"] == "abs_err" and result["n_inputs"] == 10
    for key in ("times", "traj_err", "func_err", "func_err_fp", "f_p_abs", "f_phi_abs", "correction_share"):
        assert len(result[key]) == 50 and all(math.isfinite(v) for v in result[key]), key
    assert result["func_err_fp"][-1] > 0.1, "f_p alone misses the friction"
    assert 0 < result["summary"]["correction_share"] < 1 and result["func_err_unavailable"] is None
    assert (run / "figures" / "components.png").is_file()
    logged = (run / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {"components/traj_err", "components/func_err", "components/correction_share"} <= set(logged)


def test_exact_correction_has_no_function_level_error(tmp_path):
    model, datamodule = _model(lambda *shapes: Friction()), _data(tmp_path)
    rng = model.generator.get_state()
    result = component_analysis(model, datamodule, n=6, seed=1)
    assert torch.equal(model.generator.get_state(), rng), "the analysis leaves training's draws alone"
    assert result["func_err"].shape == (50,) and result["func_err"].max() < 1e-5
    assert result["func_err_fp"][1:].min() > 1e-3 and result["summary"]["func_err_fp"] > 0.05
    assert result["traj_err"].max() < 1e-5, "solving the DGP's field reproduces the DGP's draws"
    assert result["summary"]["traj_err_fp"] > 1e-2, "f_p alone, solved from the same inputs, misses the friction"
    share = result["f_phi_abs"] / (result["f_p_abs"] + result["f_phi_abs"])
    assert torch.allclose(result["correction_share"], share) and result["f_phi_abs"][1:].min() > 0


def test_the_moving_average_is_analysed(tmp_path):
    model, datamodule = _model(partial(ConditionalMLP, output_scale=0.0), ema_decay=0.9), _data(tmp_path)
    model.map_average.module.correction = Friction()
    assert component_analysis(model, datamodule, n=4)["func_err"].max() < 1e-5


def test_random_hidden_parameters_have_no_function_level_error(tmp_path):
    datamodule = _data(tmp_path, Uniform(0.6, 1.5), draws_per_input=3)
    result = component_analysis(_model(partial(ConditionalMLP), z_dim=2), datamodule, n=4)
    assert result["func_err"] is None and result["func_err_fp"] is None and result["summary"]["func_err"] is None
    assert "random" in result["func_err_unavailable"] and result["traj_err_kind"] == "energy"
    assert result["traj_err"].shape == (50,) and torch.isfinite(result["traj_err"]).all()


@pytest.mark.parametrize("recorded", [False, True])
def test_a_measured_file_has_no_function_level_error(tmp_path, recorded):
    physics, generator = Pendulum(), torch.Generator().manual_seed(0)
    x0, theta = physics.sample_initial_state(70, generator), physics.sample_theta(70, generator)
    y = physics.with_hidden_effect([ViscousFriction(Constant(1.2))]).simulate(x0, theta, torch.full((70, 1), 1.2))
    inputs = {"x0": x0.numpy(), "theta": theta.numpy()} if recorded else {}
    np.savez(tmp_path / "m.npz", y=y.numpy(), **inputs)
    datamodule = SimulationDataModule(physics, measured_path=str(tmp_path / "m.npz"))
    datamodule.setup("validate")
    result = component_analysis(_model(lambda *shapes: Friction()), datamodule, n=10)
    assert result["mode"] == "marginal" and result["func_err"] is None and "file" in result["func_err_unavailable"]
    assert result["traj_err_kind"] == "energy" and result["traj_err"].shape == (50,)
    assert torch.isfinite(result["traj_err"]).all() and result["f_phi_abs"][1:].min() > 0
    if recorded:  # the exact map on the recorded inputs reproduces each measurement: a paired distance of 0
        assert result["traj_err"].abs().max() < 1e-4


def test_a_map_without_components_is_refused(tmp_path):
    model = MapTraining(Pendulum(), lambda physics, z: nn.Identity(), partial(MLPCritic, hidden=[8]))
    with pytest.raises(TypeError, match="needs a grey-box map with components"):
        component_analysis(model, _data(tmp_path))
