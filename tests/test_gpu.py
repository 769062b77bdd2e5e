"""GPU readiness: one short fit and test of each system on ``--trainer.accelerator gpu``, the bfloat16 C2ST, compiled solves.

Marked ``gpu``; skipped where no CUDA device is present (``pytest -m gpu`` on a GPU machine runs them).
"""

import json
import math

import pytest
import torch
from test_cli import CONFIGS, _tiny
from test_discovery import warnings_said

from otgb.cli import main
from otgb.data import generate_measured
from otgb.discovery.library import Candidate
from otgb.discovery.refine import Fitting
from otgb.metrics.c2st import c2st
from otgb.physics import AdvectionDiffusion, Augmented, Constant, LibraryTerm, ReactionDiffusion

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]
SYSTEMS = [c for c in CONFIGS if c.stem in ("pendulum", "advdiff", "reactdiff")]


@pytest.mark.parametrize("config", SYSTEMS, ids=lambda path: path.stem)
def test_fit_and_test_on_the_gpu(tmp_path, monkeypatch, config):
    monkeypatch.chdir(tmp_path)
    tiny = [*_tiny(config, tmp_path / "cache"), "--trainer.accelerator=gpu", "--trainer.devices=1"]
    main(["fit", "--config", str(config), *tiny])
    last = tmp_path / "runs" / config.stem / "version_0" / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False)["global_step"] == 4
    main(["test", "--config", str(config), *tiny, f"--ckpt_path={last}"])
    report = json.loads((tmp_path / "runs" / config.stem / "version_1" / "metrics.json").read_text())
    assert all(math.isfinite(value["mean"]) for value in report["model"].values()), report["model"]
    assert 0.0 <= report["model"]["c2st"]["mean"] <= 1.0


def test_c2st_in_bfloat16_on_the_gpu():
    g = torch.Generator().manual_seed(0)
    same = torch.randn(400, 60, generator=g).cuda(), torch.randn(400, 60, generator=g).cuda()
    shifted = same[0], same[1] + 1.0
    assert abs(float(c2st(*same, precision="bf16-mixed")["c2st"]) - 0.5) < 0.1
    assert float(c2st(*shifted, precision="bf16-mixed")["c2st"]) > 0.9


@pytest.mark.parametrize("solver", ["eager", "compiled"])
def test_the_greybox_solve_and_its_gradients_on_the_gpu_equal_torchdiffeq_there_and_on_the_cpu(solver):
    from test_solvers import _assert_same, _forward_backward, _pendulum_greybox

    greybox = _pendulum_greybox()
    on_cpu = _forward_backward(greybox, "torchdiffeq", 32)
    greybox.cuda()
    reference = _forward_backward(greybox, "torchdiffeq", 32)
    fast = _forward_backward(greybox, solver, 32)
    _assert_same(tuple(map(_to_cpu, fast)), tuple(map(_to_cpu, reference)), 1e-4)
    _assert_same(tuple(map(_to_cpu, reference)), on_cpu, 1e-4)


def _to_cpu(value):
    return [v.cpu() for v in value] if isinstance(value, list) else value.cpu()


def test_a_compiled_solve_without_gradients_on_the_gpu_keeps_every_state():
    """On a GPU each compiled step replays a CUDA graph, which writes its output where the last replay wrote it; a
    solve without gradients (f_p's simulations) keeps every state, so the states must be copies, not the graph's."""
    assert _decay_solved_without_gradients("cuda") < 1e-5


def _decay_solved_without_gradients(device: str) -> float:
    """The largest relative error of RK4 on d(state)/dt = -rate * state, against exp(-rate t), on ``device``."""
    from otgb.physics import solvers

    rate, times = torch.linspace(0.5, 2.0, 8, device=device)[:, None], torch.arange(11, device=device) * 0.1
    start = torch.ones(8, 3, device=device)
    solvers.set_solver("compiled")
    try:
        with torch.no_grad():
            states = solvers.integrate(lambda state, k: -k * state, start, (rate,), "rk4", 0.05, 0.1, 11)
    finally:
        solvers.reset()
    exact = torch.exp(-rate * times)[:, :, None].expand_as(states)
    return float(((states - exact).abs() / exact).max())


def test_coefficient_fits_on_the_gpu_reach_the_cpus_coefficients_without_falling_back():
    """otgb discover's coefficient fits on the trainer's device: a reaction-diffusion fit of the hidden reaction's cubic
    term on the GPU, no fallback warning, its coefficient and held-out score within float rounding of the CPU's."""
    physics = ReactionDiffusion(n_grid=16)
    dgp = physics.with_hidden_effect([LibraryTerm("u^3", "u", Constant(-1.0))])
    train, val, cubic = generate_measured(dgp, 120, 1)["y"], generate_measured(dgp, 40, 2)["y"], Candidate("u^3", "u")
    with warnings_said() as said:
        on_gpu = Fitting(physics, train, val, 20, 128, 0, device=torch.device("cuda"))([cubic], [-0.7])
    on_cpu = Fitting(physics, train, val, 20, 128, 0)([cubic], [-0.7])
    assert not said, said
    gpu, cpu = on_gpu.priors[0].value, on_cpu.priors[0].value
    assert abs(gpu - cpu) < 1e-3 * abs(cpu), (gpu, cpu)
    assert abs(on_gpu.heldout_energy - on_cpu.heldout_energy) < 1e-3 * abs(on_cpu.heldout_energy) + 1e-6


def test_a_term_fixed_in_space_solves_on_the_gpu_as_on_the_cpu():
    """A feature of the grid's coordinates (``s^2``) is made on the state's device inside the solve, with no copy from
    the host, which a CUDA graph's capture refuses: the compiled solve on the GPU equals the eager one on the CPU."""
    from otgb.physics import solvers

    heated = Augmented(AdvectionDiffusion(), [LibraryTerm("s^2", "T", Constant(0.5))])
    g = torch.Generator().manual_seed(0)
    x0, theta = heated.sample_initial_state(8, g), heated.sample_theta(8, g)
    on_cpu = heated.simulate(x0, theta)
    solvers.set_solver("compiled")
    try:
        with warnings_said("otgb.solvers") as said, torch.no_grad():  # where a failed compile says it runs eagerly
            on_gpu = heated.cuda().simulate(x0.cuda(), theta.cuda())
    finally:
        solvers.reset()
    assert not said, said
    assert torch.allclose(on_gpu.cpu(), on_cpu, atol=1e-5), float((on_gpu.cpu() - on_cpu).abs().max())
