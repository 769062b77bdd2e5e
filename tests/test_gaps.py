"""Measurements as a lab records them: a model read at its own times between solver steps, and missing values (NaN)
treated alike on both sides of every comparison."""

import csv
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from otgb.cli import main
from otgb.command import logger_override
from otgb.data.gaps import comparable, filled, with_gaps_of
from otgb.discovery.closer import closer
from otgb.discovery.locate import describe, locate
from otgb.discovery.paired import paired_check
from otgb.physics import Pendulum

ROOT = Path(__file__).parents[1]
CAMERA = torch.arange(148, dtype=torch.float64) / 30  # 30 frames per second up to the pendulum's horizon, 4.9 s


def pendulum_inputs(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    physics = Pendulum()
    return physics.sample_initial_state(n, g), physics.sample_theta(n, g)


def test_a_model_read_between_its_steps_keeps_the_solvers_order():
    x0, theta = pendulum_inputs(16)
    exact = Pendulum(step_size=0.1 / 64).read_at(CAMERA).simulate(x0, theta).double()
    errors = [float((Pendulum(step_size=h).read_at(CAMERA).simulate(x0, theta) - exact).abs().max()) for h in (0.1, 0.05)]
    assert 10 < errors[0] / errors[1] < 24, f"errors {errors}: RK4 with cubic Hermite reading is 4th order (ratio 16)"
    on_grid = Pendulum()
    read_on_grid = on_grid.read_at(on_grid.observation_times()).simulate(x0, theta)
    assert torch.allclose(read_on_grid, on_grid.simulate(x0, theta), atol=1e-6)
    assert on_grid.read_at(CAMERA).observation_times().shape == (148,) and "read_at(148 times in [0, 4.9]" in repr(
        on_grid.read_at(CAMERA)
    )


def test_times_outside_the_horizon_are_refused():
    with pytest.raises(ValueError, match=r"Pendulum.read_at: times in \[0, 6\] leave \[0, 4.9\]"):
        Pendulum().read_at(torch.linspace(0, 6, 10))


def test_simulations_take_the_measured_gaps_and_stay_differentiable():
    measured = torch.randn(5, 7, 1).masked_fill(torch.rand(5, 7, 1) < 0.3, float("nan"))
    simulated = torch.randn(12, 7, 1, requires_grad=True)
    a, b = comparable(simulated, measured)
    rows = torch.arange(12) % 5
    assert torch.equal(a == 0, torch.isnan(measured)[rows] | (simulated == 0)) and not b.isnan().any()
    a.sum().backward()
    assert torch.equal(simulated.grad == 0, torch.isnan(measured)[rows]), "no gradient through a missing value"
    assert with_gaps_of(simulated, torch.randn(5, 7, 1)) is simulated, "a file with no gap meets none of this"


def gappy(n: int, g: torch.Generator, share: float = 0.3, shift: float = 0.0) -> torch.Tensor:
    y = torch.randn(n, 12, 1, generator=g, dtype=torch.float64) + shift
    return y.masked_fill(torch.rand(y.shape, generator=g) < share, float("nan"))


def test_the_disagreement_map_keeps_its_level_with_gaps_where_zero_filling_alone_does_not():
    g = torch.Generator().manual_seed(3)
    times = torch.arange(12.0)
    runs = [(gappy(60, g, shift=2.0), 2 + torch.randn(60, 12, 1, generator=g, dtype=torch.float64)) for _ in range(20)]
    honest = [locate(a, b, times, ("u",), n_permutations=199, seed=i) for i, (a, b) in enumerate(runs)]
    naive = [locate(filled(a), b, times, ("u",), n_permutations=199, seed=i) for i, (a, b) in enumerate(runs)]
    assert sum(m.any_significant for m in honest) <= 3, "about alpha of the null runs may flag"
    assert all(m.any_significant for m in naive), "the check could fail: zeros on one side only are a difference"
    assert 0.3 < sum(m.whole_pvalue for m in honest) / len(honest) < 0.7, "whole-trajectory p-values about uniform"
    shifted = locate(gappy(60, g, shift=1.0), torch.randn(60, 12, 1, generator=g, dtype=torch.float64), times, ("u",))
    assert shifted.significant.all() and torch.isfinite(shifted.mean_a).all()
    assert "mean is higher (by 1" in describe(shifted)


def test_the_closer_test_and_the_paired_check_read_the_measured_values_only():
    g = torch.Generator().manual_seed(4)
    measured = gappy(40, g)
    alike = closer(torch.randn(80, 12, 1, generator=g), torch.randn(80, 12, 1, generator=g), measured, 199, 0.05, 0)
    assert not alike.significant and math.isfinite(alike.difference)
    nearer = closer(torch.randn(80, 12, 1, generator=g), torch.randn(80, 12, 1, generator=g) + 1, measured, 199, 0.05, 0)
    assert nearer.significant
    x0, theta = pendulum_inputs(30)
    physics = Pendulum()
    y = physics.simulate(x0, theta) + 0.02 * torch.randn(30, 50, 1, generator=g)
    y = y.masked_fill(torch.rand(y.shape, generator=g) < 0.2, float("nan"))
    check = paired_check(physics, y, x0, theta, 0.02)
    assert check.values == int((~y.isnan()).sum()) and check.diverged == 0 and check.pvalue > 1e-3
    assert paired_check(physics, y, x0, theta, 0.005).pvalue < 1e-6, "a noise stated too small reads as a missing effect"


def test_a_fit_on_a_lab_file_with_own_times_and_lost_frames(tmp_path):
    lab = tmp_path / "lab.csv"
    script = [sys.executable, str(ROOT / "scripts" / "scipy_lab_pendulum.py"), "--n", "160", "--missing", "0.2"]
    subprocess.run([*script, "--seed", "1", "--out", str(lab)], check=True)
    before = lab.read_bytes()
    arguments = [
        "--config",
        str(ROOT / "configs" / "pendulum.yaml"),
        logger_override(str(tmp_path), "run"),
        "--trainer.enable_progress_bar=false",
        "--trainer.val_check_interval=3",
        "--trainer.max_steps=6",
        "--data.simulation_budget=3200",
        "--data.batch_size=16",
        "--data.hidden_effect=[]",
        f"--data.measured_path={lab}",
        "--data.measurement_noise=0.02",
        "--evaluation.reference_repeats=2",
        "--evaluation.mmdagg_permutations=200",
        f"--data.cache_dir={tmp_path / 'cache'}",
    ]
    main(["fit", *arguments])
    with open(tmp_path / "run" / "version_0" / "metrics.csv") as f:
        energies = [float(r["val/energy"]) for r in csv.DictReader(f) if r.get("val/energy")]
    assert len(energies) == 2 and all(math.isfinite(e) for e in energies)
    assert lab.read_bytes() == before, "the user's file is untouched"
