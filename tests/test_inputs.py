"""Recorded inputs: a drive read between its samples by every stage of the solve, from a file's column or a declared
process, through f_p, f_phi, the training stream, the evaluation and discovery's library."""

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from otgb.cli import main
from otgb.command import logger_override
from otgb.data.files import read_measured
from otgb.data.sources import FileMeasurements, GeneratedMeasurements
from otgb.discovery.library import build_library, physical_name
from otgb.discovery.regression import design_matrix
from otgb.errors import InputError
from otgb.models import ConditionalMLP
from otgb.models.greybox import GreyBoxODE
from otgb.physics import (
    AdvectionDiffusion,
    Augmented,
    Constant,
    LibraryTerm,
    Pendulum,
    Recorded,
    SumOfSines,
    Uniform,
    ViscousFriction,
)
from otgb.physics.signals import filled, value_at

ROOT = Path(__file__).parents[1]
SINES = SumOfSines(Uniform(0.5, 1.5), Uniform(0.2, 0.8))


def sine_drive(t: np.ndarray | float, amplitude: float = 1.2, frequency: float = 0.6) -> np.ndarray | float:
    return amplitude * np.sin(2 * np.pi * frequency * t) + 0.5 * np.cos(2 * np.pi * 0.25 * t)


def inputs(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return Pendulum().sample_initial_state(n, g), Pendulum().sample_theta(n, g)


def test_a_driven_solve_matches_scipy_and_keeps_the_solvers_order():
    x0, theta = inputs(6)
    errors = []
    for step in (0.1, 0.05):
        model = Pendulum(step_size=step)
        times = torch.arange(0, 5.0 + 1e-9, step / 3, dtype=torch.float64)
        recorded = Recorded(times.float(), torch.from_numpy(sine_drive(times.numpy()))[None, :, None].expand(6, -1, -1))
        driven = model.driven_by(recorded)
        y = driven.simulate(x0, theta, signals=driven.sample_signals(6, torch.Generator())).double()
        worst = 0.0
        for i in range(6):
            omega = float(theta[i, 0])
            solved = solve_ivp(
                lambda t, s, w: [s[1], -(w**2) * np.sin(s[0]) + sine_drive(t)], (0, 4.9), x0[i].double().numpy(),
                t_eval=np.arange(50) * 0.1, args=(omega,), rtol=1e-11, atol=1e-12, method="DOP853",
            )  # fmt: skip
            worst = max(worst, float(np.abs(solved.y[0] - y[i, :, 0].numpy()).max()))
        errors.append(worst)
    assert errors[1] < 1e-3 and errors[0] / errors[1] > 6, f"errors {errors}: each RK4 stage reads the drive at its own time"


def test_zero_signals_give_the_undriven_solve_and_a_drive_changes_it():
    x0, theta = inputs(8)
    model = Pendulum(drive=SINES)
    signals = model.sample_signals(8, torch.Generator().manual_seed(1))
    assert signals.shape == (8, len(model.signal_times()), 1) and model.is_driven and not Pendulum().is_driven
    undriven = Pendulum().simulate(x0, theta)
    assert torch.allclose(model.simulate(x0, theta, signals=torch.zeros_like(signals)), undriven, atol=1e-5)
    assert (model.simulate(x0, theta, signals=signals) - undriven).abs().max() > 0.1
    read = model.read_at(torch.tensor([0.0, 0.37, 2.0, 4.9]))
    assert torch.allclose(
        read.simulate(x0, theta, signals=signals)[:, [0, 3]], model.simulate(x0, theta, signals=signals)[:, [0, 49]], atol=1e-5
    )
    with pytest.raises(InputError, match=r"Pendulum.solve: signals have shape \(8, 3, 1\), expected \(8, 152, 1\)"):
        model.simulate(x0, theta, signals=signals[:, :3])


def test_signals_read_linearly_and_gaps_fill_between_recorded_samples():
    times = torch.tensor([0.0, 1.0, 2.0, 4.0])
    values = torch.tensor([[[0.0], [2.0], [float("nan")], [8.0]], [[float("nan")], [1.0], [1.0], [float("nan")]]])
    full = filled(times, values)
    assert torch.equal(full[:, :, 0], torch.tensor([[0.0, 2.0, 4.0, 8.0], [1.0, 1.0, 1.0, 1.0]]))
    read = value_at(times, full, torch.tensor([0.5, 9.0]))
    assert torch.allclose(read[:, 0], torch.tensor([1.0, 1.0]))


def test_inputs_a_hidden_effect_and_an_augmented_term_read_alike():
    """A drive gain that f_p misses: the DGP's term, the same LibraryTerm in an augmented model, and the drive scaled."""
    x0, theta = inputs(8)
    model = Pendulum(drive=SINES)
    dgp = model.with_hidden_effect([LibraryTerm("drive", "velocity", Constant(-0.4))])
    signals = model.sample_signals(8, torch.Generator().manual_seed(2))
    y = dgp.simulate(x0, theta, dgp.sample_effect_params(8, torch.Generator()), signals)
    assert torch.allclose(y, model.simulate(x0, theta, signals=0.6 * signals), atol=1e-5)
    augmented = Augmented(model, [LibraryTerm("drive", "velocity", Constant(-0.4))])
    assert torch.allclose(augmented.simulate(x0, torch.cat([theta, torch.full((8, 1), -0.4)], 1), signals=signals), y)


def test_the_library_offers_the_inputs_and_evaluates_them_along_trajectories():
    model = Pendulum(drive=SINES)
    features = [c.feature for c in build_library(model, ["velocity"])]
    assert {"drive", "drive*velocity", "drive*cos(angle)"} <= set(features)
    assert not any("drive" in f for f in (c.feature for c in build_library(Pendulum(), ["velocity"]))), "undriven: none"
    assert "mis-scaled or missing input gain" in physical_name("drive", "velocity", -0.4, model)
    states, theta = torch.randn(4, 5, 2), torch.rand(4, 1)
    drive = torch.randn(4, 5, 1)
    candidates = [c for c in build_library(model, ["velocity"]) if c.feature in ("drive", "drive*cos(angle)")]
    design = design_matrix(model, candidates, states, theta, torch.zeros(4, 5), inputs=drive)
    expected = np.stack([drive.flatten().numpy(), (drive[..., 0] * torch.cos(states[..., 0])).flatten().numpy()], 1)
    assert np.allclose(design.X, expected, atol=1e-6)


def test_the_greybox_correction_sees_the_inputs():
    model = Pendulum(drive=SINES)
    grey = GreyBoxODE(model, 0, lambda s, c, k: ConditionalMLP(s, c, k))
    assert grey.correction.hidden[0].in_features - 16 == 3, "angle, velocity and drive"
    x0, theta = inputs(4)
    signals = model.sample_signals(4, torch.Generator().manual_seed(3))
    parts = grey.components(x0, theta, torch.zeros(4, 0), signals)
    assert parts["inputs"].shape == (4, 50, 1)
    assert torch.allclose(parts["inputs"][:, :, 0], model.inputs_along(signals)[:, :, 0])
    assert GreyBoxODE(Pendulum(), 0, lambda s, c, k: ConditionalMLP(s, c, k)).correction.hidden[0].in_features == 2 + 16


def driven_csv(tmp_path: Path, n: int = 160, seed: int = 1) -> Path:
    lab = tmp_path / "driven.csv"
    script = [sys.executable, str(ROOT / "scripts" / "scipy_lab_pendulum.py"), "--n", str(n), "--missing", "0.2"]
    subprocess.run([*script, "--drive", "1.0", "--seed", str(seed), "--out", str(lab)], check=True)
    return lab


def test_a_drive_column_drives_the_model_with_no_other_setting(tmp_path):
    lab = driven_csv(tmp_path, n=60)
    file = read_measured(lab, Pendulum())
    assert file.u is not None and file.u.shape[:2] == file.y.shape[:2] and file.u.isnan().any(), "rows left out: missing"
    source = FileMeasurements(Pendulum(), str(lab), 0.2, 0.2, seed=0)
    assert source.physics.is_driven and source.records_signals and "recorded drive" in source.describe()
    test = source.evaluation_set("test", len(source.parts["test"]))
    assert test["signals"].shape == (len(source.parts["test"]), file.y.shape[1], 1) and not test["signals"].isnan().any()
    assert source.evaluation_plan()[""][2], "a draw on a trajectory's own drive is scored across halves"
    rows = source.physics.sample_signals(50, torch.Generator().manual_seed(0))
    train = source.training_signals()
    assert all(any(torch.equal(r, t) for t in train) for r in rows), "simulations take the training part's recorded drives"


def test_recorded_inputs_are_checked(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("trajectory,t,angle,drive\n0,0,0.1,\n0,0.1,0.2,\n0,0.2,0.3,\n")
    with pytest.raises(InputError, match=r"trajectory 0 has no recorded value of 'drive', expected at least one"):
        read_measured(bad, Pendulum())
    bad.write_text("trajectory,t,angle,drive\n0,0,0.1,1\n0,0.1,0.2,inf\n0,0.2,0.3,1\n")
    with pytest.raises(InputError, match=r"line 3: trajectory 0 at t=0.1: 'drive' is inf, expected a finite number"):
        read_measured(bad, Pendulum())
    npz = tmp_path / "bad.npz"
    np.savez(npz, y=np.zeros((4, 50, 1)), u=np.zeros((4, 49, 1)))
    with pytest.raises(InputError, match=r"'u' has shape \(4, 49, 1\), expected \(4, 50, 1\): the inputs \('drive',\)"):
        read_measured(npz, Pendulum())


def test_a_generated_dgp_draws_its_drive_from_the_declared_process(tmp_path):
    physics = Pendulum(drive=SINES)
    source = GeneratedMeasurements(physics, [ViscousFriction(Constant(0.8))], 32, 1, 0, str(tmp_path))
    joint = source.evaluation_set("val", 16)
    assert joint["signals"].shape == (16, len(physics.signal_times()), 1)
    again = GeneratedMeasurements(physics, [ViscousFriction(Constant(0.8))], 32, 1, 0, str(tmp_path / "other"))
    assert torch.equal(again.evaluation_set("val", 16)["y"], joint["y"]), "the same seed, the same drives and data"
    undriven = GeneratedMeasurements(Pendulum(), [ViscousFriction(Constant(0.8))], 32, 1, 0, str(tmp_path))
    assert (undriven.evaluation_set("val", 16)["y"] - joint["y"]).abs().max() > 0.05


def test_a_fit_on_a_driven_lab_file(tmp_path):
    lab = driven_csv(tmp_path)
    before = lab.read_bytes()
    arguments = [
        "--config", str(ROOT / "configs" / "pendulum.yaml"), logger_override(str(tmp_path), "run"),
        "--trainer.enable_progress_bar=false", "--trainer.val_check_interval=3", "--trainer.max_steps=6",
        "--data.simulation_budget=3200", "--data.batch_size=16", "--data.hidden_effect=[]", f"--data.measured_path={lab}",
        "--data.measurement_noise=0.02", "--evaluation.reference_repeats=2", "--evaluation.mmdagg_permutations=200",
        f"--data.cache_dir={tmp_path / 'cache'}",
    ]  # fmt: skip
    main(["fit", *arguments])
    with open(tmp_path / "run" / "version_0" / "metrics.csv") as f:
        energies = [float(r["val/energy"]) for r in csv.DictReader(f) if r.get("val/energy")]
    assert len(energies) == 2 and all(math.isfinite(e) for e in energies)
    weights = torch.load(tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    first = next(v for k, v in weights.items() if k.startswith("transport_map.correction.hidden.0.weight"))
    assert first.shape[1] == 3 + 16, "f_phi takes angle, velocity and the drive beside the condition's code"
    assert lab.read_bytes() == before, "the user's file is untouched"


def test_the_rods_heater_power_warms_every_point_alike():
    rod = AdvectionDiffusion(power=SumOfSines(Uniform(0.5, 1.0), Uniform(0.5, 1.0)))
    g = torch.Generator().manual_seed(0)
    x0, theta = rod.sample_initial_state(4, g), rod.sample_theta(4, g)
    signals = rod.sample_signals(4, g)
    assert signals.shape == (4, len(rod.signal_times()), 1)
    heated, cold = rod.simulate(x0, theta, signals=signals), rod.simulate(x0, theta)
    state = torch.randn(4, 1, 20)
    assert torch.allclose(rod.field(state, theta, torch.ones(4, 1)) - rod.field(state, theta), torch.ones(4, 1, 20))
    assert (heated - cold).abs().max() > 1e-3 and rod.is_driven


def test_the_next_round_of_a_driven_dgp_reads_its_drive_from_the_file(tmp_path):
    source = GeneratedMeasurements(Pendulum(drive=SINES), [ViscousFriction(Constant(0.8))], 40, 1, 0, str(tmp_path))
    (tmp_path / "round").mkdir()
    path = source.as_file(tmp_path / "round", source.measured_set())
    again = FileMeasurements(Pendulum(), path, 0.25, 0.25, seed=0)
    assert again.physics.is_driven and again.file.u.shape == (40, 50, 1)
    exact = source.dgp.inputs_along(source._generated()["signals"])
    assert torch.allclose(again.file.u, exact)
