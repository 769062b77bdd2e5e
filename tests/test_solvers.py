"""The fast solve path against torchdiffeq's, the reference: same trajectories and gradients, compiled once."""

import json
import logging
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from logcapture import records_of

from otgb.models import ConditionalConvNet, ConditionalMLP, GreyBoxODE
from otgb.physics import (
    Advection,
    AdvectionDiffusion,
    Augmented,
    Constant,
    FitzHughNagumoReaction,
    LibraryTerm,
    Pendulum,
    ReactionDiffusion,
    ViscousFriction,
    solvers,
)

ROOT = Path(__file__).parents[1]


def _systems():
    pendulum = Pendulum()
    return {
        "pendulum": pendulum,
        "pendulum + friction": pendulum.with_hidden_effect([ViscousFriction(Constant(1.2))]),
        "pendulum, euler at dt/4": Pendulum(method="euler", step_size=0.025),
        "pendulum, midpoint": Pendulum(method="midpoint"),
        "pendulum, heun2": Pendulum(method="heun2"),
        "pendulum, heun3": Pendulum(method="heun3"),
        "augmented pendulum": Augmented(Pendulum(), [LibraryTerm("velocity", "velocity", Constant(-1.2))]),
        "advection-diffusion + advection": AdvectionDiffusion().with_hidden_effect([Advection(Constant(0.1))]),
        "reaction-diffusion + u-reaction": ReactionDiffusion(n_grid=8, u_reaction=False).with_hidden_effect(
            [FitzHughNagumoReaction(Constant(5e-3))], step_size=0.05
        ),
    }


def _simulate(model, solver: str, n: int = 6) -> torch.Tensor:
    solvers.set_solver(solver)
    g = torch.Generator().manual_seed(0)
    x0, theta = model.sample_initial_state(n, g), model.sample_theta(n, g)
    return model.simulate(x0, theta, model.sample_effect_params(n, g))


@pytest.mark.parametrize("name", list(_systems()))
def test_eager_trajectories_equal_torchdiffeq(name):
    model = _systems()[name]
    reference, fast = _simulate(model, "torchdiffeq"), _simulate(model, "eager")
    scale = reference.abs().max()
    assert fast.shape == reference.shape
    assert (fast - reference).abs().max() <= 1e-5 * scale, "the same method on the same grid, to float32 rounding"


def _compile_counts() -> dict[str, int]:
    """Graphs torch.compile has built and recompiles it made in this process."""
    from torch._dynamo.utils import counters

    return {"graphs": int(counters["stats"]["unique_graphs"]), "recompiles": int(sum(counters["recompiles"].values()))}


def _pendulum_greybox(z_dim: int = 2) -> GreyBoxODE:
    torch.manual_seed(0)
    return GreyBoxODE(Pendulum(), z_dim, lambda s, c, d: ConditionalMLP(s, c, d, hidden=(64, 64)))


def _advdiff_greybox() -> GreyBoxODE:
    torch.manual_seed(0)
    return GreyBoxODE(AdvectionDiffusion(n_obs=8), 1, lambda s, c, d: ConditionalConvNet(s, c, d, output_scale=1.0))


def _forward_backward(greybox: GreyBoxODE, solver: str, n: int) -> tuple[torch.Tensor, list[torch.Tensor]]:
    solvers.set_solver(solver)
    g = torch.Generator().manual_seed(1)
    physics = greybox.physics
    x0, theta, z = physics.sample_initial_state(n, g), physics.sample_theta(n, g), torch.randn(n, greybox.z_dim, generator=g)
    device = next(greybox.parameters()).device
    greybox.zero_grad()
    y = greybox(None, x0.to(device), theta.to(device), z.to(device))
    (y * torch.linspace(-1, 1, y[0].numel(), device=device).reshape(y.shape[1:])).sum().backward()
    return y.detach(), [p.grad.clone() for p in greybox.parameters()]


def _assert_same(fast, reference, tolerance: float) -> None:
    (y, grads), (y_ref, grads_ref) = fast, reference
    assert (y - y_ref).abs().max() <= tolerance * y_ref.abs().max()
    for grad, grad_ref in zip(grads, grads_ref):
        assert (grad - grad_ref).abs().max() <= tolerance * grad_ref.abs().max().clamp_min(1e-12)


@pytest.mark.parametrize("make", [_pendulum_greybox, _advdiff_greybox], ids=["pendulum", "advection-diffusion"])
def test_eager_greybox_gradients_equal_torchdiffeq(make):
    greybox = make()
    _assert_same(_forward_backward(greybox, "eager", 8), _forward_backward(greybox, "torchdiffeq", 8), 1e-4)


def test_compiled_greybox_equals_torchdiffeq_and_compiles_once_for_every_batch_size():
    greybox = _pendulum_greybox()
    before = _compile_counts()
    _assert_same(_forward_backward(greybox, "compiled", 32), _forward_backward(greybox, "torchdiffeq", 32), 1e-4)
    _forward_backward(greybox, "compiled", 32)
    after_training = _compile_counts()
    assert after_training["graphs"] - before["graphs"] == 1, "one graph for the differentiated step"
    _forward_backward(greybox, "compiled", 13)  # a partial last batch
    with torch.no_grad():
        for n in (64, 20):  # validation and test sizes
            greybox(None, *_inputs(greybox, n))
    after = _compile_counts()
    assert after["graphs"] - after_training["graphs"] == 1, "one more graph for solves without gradients, whatever the size"
    assert after["recompiles"] == before["recompiles"]


def _inputs(greybox: GreyBoxODE, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(2)
    physics = greybox.physics
    return physics.sample_initial_state(n, g), physics.sample_theta(n, g), torch.randn(n, greybox.z_dim, generator=g)


def test_auto_solves_eagerly_until_a_models_field_has_been_solved_often(monkeypatch):
    monkeypatch.setattr(solvers, "COMPILE_AFTER", 3)
    compiled_solves = []

    def recording_solve(device_type):
        return lambda *args: compiled_solves.append(1) or solvers.whole_solve(*args)

    monkeypatch.setattr(solvers, "compiled_whole_solve", recording_solve)
    counts, pendulum = [], Pendulum()
    with torch.no_grad(), records_of("otgb.solvers") as records:
        for _ in range(4):
            _simulate(pendulum, "auto")
            counts.append(len(compiled_solves))
        _simulate(Pendulum(), "auto")
    assert counts == [0, 0, 0, 1], "the 4th solve of the model's field is its first compiled one"
    assert len(compiled_solves) == 1, "another model (as each of discovery's fits makes) counts its own solves"
    assert [r.getMessage() for r in records] == [
        "otgb: compiling the solve of Pendulum.vector_field (solver auto: 3 solves of it run or planned): once a run, a "
        "minute or more on a few cores, less where torch's compile cache holds it"
    ], "a compile is announced once, when it starts"


def test_a_small_state_is_solved_as_one_compiled_loop_and_a_field_step_by_step(monkeypatch):
    calls = []
    monkeypatch.setattr(solvers, "compiled_whole_solve", lambda d: lambda *a: calls.append("whole") or solvers.whole_solve(*a))
    monkeypatch.setattr(solvers, "compiled_step", lambda m, d: lambda *a: calls.append("step") or solvers.STEPS[m](*a))
    with torch.no_grad():
        _simulate(Pendulum(), "compiled")
        assert calls == ["whole"]
        _simulate(ReactionDiffusion(n_grid=8, n_obs=3), "compiled")  # a state of 2 x 8 x 8 numbers
    assert calls[1:] == ["step"] * 3, "its 3 frames after the initial state, one compiled step each"


@pytest.mark.slow
@pytest.mark.parametrize("name", list(_systems()))
def test_compiled_trajectories_and_input_gradients_equal_torchdiffeq(name):
    model = _systems()[name]
    results = {}
    for solver in ("torchdiffeq", "compiled"):
        solvers.set_solver(solver)
        g = torch.Generator().manual_seed(0)
        x0, theta = model.sample_initial_state(6, g).requires_grad_(), model.sample_theta(6, g).requires_grad_()
        y = model.simulate(x0, theta, model.sample_effect_params(6, g))
        weights = torch.linspace(-1, 1, y[0].numel()).reshape(y.shape[1:])
        results[solver] = (y.detach(), torch.autograd.grad((y * weights).sum(), (x0, theta)))
    (y, grads), (y_ref, grads_ref) = results["compiled"], results["torchdiffeq"]
    assert (y - y_ref).abs().max() <= 1e-5 * y_ref.abs().max()
    for grad, grad_ref in zip(grads, grads_ref):
        assert (grad - grad_ref).abs().max() <= 1e-4 * grad_ref.abs().max().clamp_min(1e-12)


def _branching_field(state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """A vector field with data-dependent Python control flow, which torch.compile cannot trace whole."""
    if bool(state.abs().max() > 100.0):
        return -state
    return torch.stack([state[:, 1], -(theta[:, 0] ** 2) * torch.sin(state[:, 0])], dim=1)


def test_a_field_that_cannot_be_compiled_runs_eagerly_with_one_line():
    model = Pendulum()
    g = torch.Generator().manual_seed(0)
    x0, theta = model.sample_initial_state(4, g), model.sample_theta(4, g)
    solvers.set_solver("torchdiffeq")
    reference = model.solve(_branching_field, x0, theta)
    solvers.set_solver("compiled")
    with records_of("otgb.solvers", level=logging.WARNING) as records:
        fast = model.solve(_branching_field, x0, theta)
        again = model.solve(_branching_field, x0, theta)
    assert torch.allclose(fast, reference, atol=1e-6) and torch.equal(fast, again)
    lines = [r.getMessage() for r in records]
    assert len(lines) == 1 and lines[0].startswith("otgb: the solve of _branching_field runs eagerly: it could not be compiled (")


def test_an_input_error_in_the_field_is_raised_not_hidden_by_the_fallback():
    model = Pendulum()
    solvers.set_solver("compiled")
    with pytest.raises(RuntimeError), records_of("otgb.solvers", level=logging.WARNING) as records:
        model.solve(model.vector_field, torch.zeros(3, 2), torch.zeros(5, 1))  # theta of another batch
    assert not records


def _fit(tmp_path: Path, solver: str) -> list[dict]:
    from test_cli import _args, _rows

    from otgb.cli import main

    main(["fit", *_args(tmp_path / solver, "--trainer.max_steps=50", "--trainer.val_check_interval=25", f"--solver={solver}")])
    return _rows(tmp_path / solver / "run" / "version_0")


@pytest.mark.slow
def test_a_50_step_pendulum_fit_gives_the_same_curve_on_the_compiled_path(tmp_path):
    reference, fast = _fit(tmp_path, "torchdiffeq"), _fit(tmp_path, "compiled")
    for key in ("train/map_loss", "train/critic_loss", "val/abs_err"):
        ref = [float(r[key]) for r in reference if r.get(key)]
        new = [float(r[key]) for r in fast if r.get(key)]
        assert len(ref) == len(new) > 1
        assert torch.allclose(torch.tensor(new), torch.tensor(ref), rtol=2e-3, atol=1e-4), key


def test_an_unknown_solver_is_one_line_status_2_and_writes_nothing(tmp_path, monkeypatch, capsys):
    from otgb.cli import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", str(ROOT / "configs" / "pendulum.yaml"), "--solver", "fast"])
    assert exit_info.value.code == 2
    expected = "otgb: error: --solver='fast' is invalid; expected one of auto, compiled, eager, torchdiffeq"
    assert capsys.readouterr().err.splitlines() == [expected]
    assert list(tmp_path.iterdir()) == []


def test_the_speed_table_in_the_docs_is_what_the_result_files_give(tmp_path):
    doc = tmp_path / "results.md"
    doc.write_text((ROOT / "docs" / "results.md").read_text())
    script = ROOT / "scripts" / "speed_benchmark.py"
    results = ROOT / "results" / "speed"
    subprocess.run([sys.executable, str(script), "table", "--out", str(results), "--doc", str(doc)], check=True)
    assert doc.read_text() == (ROOT / "docs" / "results.md").read_text()


def test_profile_step_splits_a_step_into_its_parts_and_counts_the_scalar_reads():
    script = ROOT / "scripts" / "profile_step.py"
    command = [sys.executable, str(script), "--config", str(ROOT / "configs" / "pendulum.yaml"), "--steps", "2"]
    done = subprocess.run([*command, "--batch-size", "4", "--solver", "eager", "--trace", "5"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "ms per training step (T_max = 1, batch 4" in lines[0] and "solver eager" in lines[0], lines[0]
    parts = {line.strip().split("  ")[0] for line in lines[1:9]}
    assert {"simulate f_p", "map forward (grey-box solve)", "map backward", "critic backward"} <= parts, parts
    assert re.match(r"scalar reads from the device in 2 steps: \d+ ", lines[-1]), lines[-1]


def test_the_gpu_benchmark_ends_by_its_deadline_and_keeps_each_parts_log(tmp_path):
    """A lent GPU's call has a hard limit: the script must end inside the seconds it is given, whatever its parts do
    (here, on a machine without a GPU, the CPU part is cut short and the GPU parts fail)."""
    start = time.monotonic()
    subprocess.run(["bash", "scripts/gpu_benchmark.sh", str(tmp_path / "out"), "20"], cwd=ROOT, capture_output=True)
    assert time.monotonic() - start < 20 + 10  # the parts' kill grace
    logs = {"machine.log", "cpu2.log", "gpu.log", "pytest-gpu.log", "profile-gpu.log"}
    assert logs <= {path.name for path in (tmp_path / "out").iterdir()}


def test_the_judges_benchmarks_references_train_on_autograd_where_otgbs_judge_trains_on_the_fused_loops(monkeypatch):
    """Otherwise, in float32 on a CPU, the library's convolution would be timed on otgb's own training step."""
    import importlib.util

    from otgb.metrics import fused_judge
    from otgb.metrics.classifiers import PaperConvClassifier

    if not fused_judge.usable():
        pytest.skip("no numba: no fused loops to keep the references off")
    spec = importlib.util.spec_from_file_location("speed_benchmark", ROOT / "scripts" / "speed_benchmark.py")
    benchmark = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(benchmark)
    fused_steps = []
    original = fused_judge.set_log_loss_gradients
    monkeypatch.setattr(fused_judge, "set_log_loss_gradients", lambda *a: fused_steps.append(1) or original(*a))
    rows, labels = benchmark.judge_rows(64, 16)
    for judge in (benchmark.LibraryConvJudge, benchmark.TorchOpsJudge, PaperConvClassifier):
        fused_steps.clear()
        judge(max_epochs=1, precision="32-true").fit(rows, labels)
        assert bool(fused_steps) == (judge is PaperConvClassifier), judge.__name__


def test_the_solve_designs_are_recorded_under_their_label_with_the_machine(tmp_path):
    script = ROOT / "scripts" / "speed_benchmark.py"
    command = [sys.executable, str(script), "designs", "--out", str(tmp_path), "--device", "cpu", "--label", "here"]
    subprocess.run([*command, "--repeats", "2", "--only", "eager", "torchdiffeq"], check=True, capture_output=True)
    results = json.loads((tmp_path / "designs.json").read_text())
    assert sorted(results) == ["pendulum-here/eager loop", "pendulum-here/torchdiffeq"]
    assert results["pendulum-here/torchdiffeq"]["max_difference"] < 1e-4
    assert results["pendulum-here/eager loop"]["machine"].startswith(("x86_64", "aarch64", "arm64", "i386"))


def test_compiled_gradients_that_differ_from_the_eager_loop_make_the_field_run_eagerly_with_one_line(monkeypatch):
    """As torch 2.11's compiled loop did (right trajectories, parameter gradients near zero): caught on the first solve."""
    monkeypatch.setattr(solvers, "compiled_whole_solve", lambda d: lambda *args: solvers.whole_solve(*args).detach())
    greybox = _pendulum_greybox()
    reference = _forward_backward(greybox, "torchdiffeq", 8)
    with records_of("otgb.solvers", level=logging.WARNING) as records:
        first, second = _forward_backward(greybox, "compiled", 8), _forward_backward(greybox, "compiled", 8)
    _assert_same(first, reference, 1e-4)
    _assert_same(second, reference, 1e-4)
    lines = [r.getMessage() for r in records]
    assert len(lines) == 1 and "runs eagerly: its compiled gradients differ from the eager loop's" in lines[0], lines


def test_compiling_quiets_torch_s_value_range_warnings_unless_the_user_set_that_logger(monkeypatch):
    from otgb.compiling import compile_generic

    sympy_log = logging.getLogger("torch.utils._sympy.interp")
    monkeypatch.setattr(sympy_log, "level", logging.NOTSET)
    compile_generic(torch.sin)
    assert sympy_log.level == logging.ERROR
    sympy_log.setLevel(logging.DEBUG)
    compile_generic(torch.sin)
    assert sympy_log.level == logging.DEBUG


def test_compiled_select_and_slice_copies_equal_the_library_s_and_are_fused():
    """otgb.compiling lowers select_copy / slice_copy (what a differentiated compiled loop makes of views) into the
    compiler's kernels: the same values as eager, for every batch size of one shape-generic graph."""
    from torch._inductor import lowering

    from otgb.compiling import compile_generic

    def copies(x: torch.Tensor) -> torch.Tensor:
        return torch.select_copy(x, 1, 0) * 2 + torch.slice_copy(x, 1, 1, 3).sum(1) - torch.slice_copy(x, 0, 1).mean()

    compiled = compile_generic(copies, cpp_wrapper=True)
    assert torch.ops.aten.select_copy.int in lowering.lowerings and torch.ops.aten.slice_copy.Tensor in lowering.lowerings
    for batch in (5, 9):
        x = torch.randn(batch, 4)
        assert torch.allclose(compiled(x), copies(x), atol=1e-6)
