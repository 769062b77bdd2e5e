"""The fast solve path against torchdiffeq's, in one run: ratios per system, warm-up counted.

    python scripts/speed_benchmark.py steps --out results/speed [--configs pendulum advdiff reactdiff] [--steps 40]
    python scripts/speed_benchmark.py fit --out results/speed --config reactdiff -- --data.simulation_budget=1600
    python scripts/speed_benchmark.py judges --out results/speed [--rows 6000 --features 1041]
    python scripts/speed_benchmark.py designs --out results/speed [--config pendulum]
    python scripts/speed_benchmark.py discover --out results/speed --measured FILE -- --data.simulation_budget=32000
    python scripts/speed_benchmark.py table --out results/speed --doc docs/results.md

``steps`` trains each config with a real Lightning Trainer for ``--steps`` training steps, once
per solver (``--solvers``, torchdiffeq first), in this one process, alternating the solvers
``--rounds`` times so that a slow spell of the machine hits both. Each step is timed whole
(loading and simulating its batch, map and critic updates, logging); the solves of the data
sets before training and the validation after it are not in these figures (``fit`` has them). It prints and writes ``steps.json``:

- per solver, the median step after the first ``--warmup`` steps, and the first run's warm-up
  seconds (where the compiled path compiles its steps, from torch's on-disk cache if it has
  them; later runs in the same process reuse the compiled graphs);
- the speed-up (reference median / fast median) and the number of steps after which the fast
  path has paid for its warm-up.

``fit`` runs ``otgb fit --config <config> --solver S`` for each solver as a whole command (import,
data, compile, training, validation, test-free), alternating ``--rounds`` times, and writes
``fit.json`` with each run's wall time, under ``--label`` (default: the config) when the overrides
differ between runs of one config. ``--cold-cache`` gives each fit an empty compile cache (what a
new machine pays): ``fit --config pendulum --solvers eager compiled --cold-cache --label
pendulum-500-steps -- --data.simulation_budget=16000`` and the same at 1500 steps measure where
``auto``'s compile pays for itself (``COMPILE_AFTER`` in otgb.physics.solvers).

``judges`` times the paper's C2ST judge (``classifier="paper"``) on rows of the Adv-diff-m-m test
draws' size: seconds per training epoch of one fold on otgb's path (on a CPU, the fused loops of
``otgb.metrics.fused_judge``), on otgb's torch operations (its path on a GPU or without numba) and
on the library's convolution (``torch.nn.Conv1d``, the reference), alternating ``--rounds`` times; the same for a 5-fold C2ST
of ``--epochs`` epochs a fold with the folds in threads (otgb's default on a CPU) and one after
the other (``n_jobs=1``), seconds per fold-epoch. The rows are Gaussian, the two samples 2 %
apart in mean and 5 % in scale: close enough that the judge trains long. Then, on these rows
and on rows it separates (the second sample's mean shifted by a sine along the row), one fold
trained with no tolerance on the held-out loss (up to ``--stop-cap`` epochs) and with the
judge's own (the paper's 1e-4): epochs, wall time and accuracy on the fold's test rows. Last, whole 5-fold C2STs
on otgb's path on both kinds of rows and on the Adv-diff-m-m test set's rows as ``otgb test`` scores f_p alone
(its draws generated into ``--out``/cache) (wall time). It writes ``judges.json``.

``designs`` measures the ways a solve can be compiled, on the grey-box map of ``--config`` (its
initial network, a batch of the config's size): the median time of one solve and its backward,
and the compile time, for torchdiffeq, the eager Runge-Kutta loop, one compiled step per call
(otgb's path for fields on grids), a compiled block of ``--block`` steps per call, and the whole solve as one
compiled ``scan`` (torch's prototype loop operator; otgb's path for small states); with the largest difference to the eager
trajectories. It writes ``designs.json``.

``discover`` runs ``otgb discover --config <config> --data.measured_path FILE`` (no hidden effect
configured) for each solver in turn, and writes ``discover.json`` with each run's wall time and the
terms it named with their coefficients.

Each writes its results as it goes; a rerun skips what is done. ``table`` writes the figures of
both files into ``--doc`` between the markers ``<!-- speed: scripts/speed_benchmark.py -->`` and
``<!-- end speed -->`` (appended when missing), so the docs' figures come from the result files.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from lightning import Callback
from result_tables import header, read_json, row

from otgb.metrics.classifiers import PaperConvClassifier, PaperConvNet
from otgb.reports import write_between

ROOT = Path(__file__).parents[1]


class StepTimes(Callback):
    """The wall time of each training step, from the end of the one before (or the start of training) to its end.

    So a step holds its batch's f_p simulation (the data module's ``on_after_batch_transfer``,
    which runs before ``on_train_batch_start``) and the logging after it.
    """

    def __init__(self) -> None:
        self.times: list[float] = []
        self._last = 0.0

    def on_train_start(self, *args) -> None:
        self._last = time.perf_counter()

    def on_train_batch_end(self, *args) -> None:
        now = time.perf_counter()
        self.times.append(now - self._last)
        self._last = now


def time_steps(config: str, solver: str, steps: int, workdir: Path, overrides: list[str]) -> tuple[list[float], bool]:
    """The wall time of each training step of ``config``, and whether they ran on a GPU."""
    from otgb.command import logger_override
    from otgb.runs import load_run

    timer = StepTimes()
    args = [
        str(ROOT / "configs" / f"{config}.yaml"), logger_override(str(workdir / "runs"), f"{config}-{solver}"),
        "--trainer.enable_progress_bar=false", f"--trainer.max_steps={steps}", f"--trainer.val_check_interval={steps}",
        "--components.enabled=false", f"--data.cache_dir={workdir / 'cache'}",
        f"--solver={solver}", *overrides,
    ]  # fmt: skip
    run = load_run(args[0], *args[1:])
    run.trainer.callbacks.append(timer)
    run.trainer.fit(run.model, run.datamodule)
    return timer.times, run.trainer.strategy.root_device.type == "cuda"


def summary(times: list[float], warmup: int) -> dict[str, float]:
    median_ms = 1000 * statistics.median(times[warmup:])
    return {"median_ms": median_ms, "warmup_s": sum(times[:warmup]), "steps": len(times), "threads": torch.get_num_threads()}


def run_steps(args: argparse.Namespace) -> None:
    from otgb.runs import machine

    out = Path(args.out)
    path, results = results_file(args, "steps.json")
    for config in args.configs:
        label = f"{config}-{args.label}" if args.label else config
        for round_ in range(args.rounds):
            for solver in args.solvers:
                key = f"{label}/{solver}/{round_}"
                if key in results:
                    continue
                times, gpu = time_steps(config, solver, args.steps, out, args.overrides)
                results[key] = summary(times, args.warmup) | {"overrides": args.overrides, "machine": machine(gpu)}
                path.write_text(json.dumps(results, indent=1))
        print(report(results, label, args.solvers), flush=True)
    print(f"speed_benchmark: wrote {path}")


def report(results: dict, config: str, solvers: list[str]) -> str:
    """One line per solver: median ms per step, speed-up over the first solver, warm-up, and when the warm-up is repaid."""
    reference = _median(results, f"{config}/{solvers[0]}/", "median_ms")
    reference_warmup = _median(results, f"{config}/{solvers[0]}/", "warmup_s")
    lines = [f"{config} (torch threads {torch.get_num_threads()}):"]
    for solver in solvers:
        prefix = f"{config}/{solver}/"
        step, warmup = _median(results, prefix, "median_ms"), _median(results, prefix, "warmup_s")
        saved_s = (reference - step) / 1000
        repaid = ""
        if solver != solvers[0] and saved_s > 0:
            repaid = f", warm-up repaid after {max(0.0, warmup - reference_warmup) / saved_s:.0f} steps"
        each = ", ".join(format(v["median_ms"], ".1f") for k, v in results.items() if k.startswith(prefix))
        speedup = reference / step
        lines.append(f"  {solver:12s} {step:8.1f} ms/step  x{speedup:5.2f}  warm-up {warmup:6.1f} s (runs: {each}){repaid}")
    return "\n".join(lines)


def results_file(args: argparse.Namespace, name: str) -> tuple[Path, dict]:
    """``<out>/<name>`` (``out`` created) and what it holds so far."""
    Path(args.out).mkdir(parents=True, exist_ok=True)
    path = Path(args.out) / name
    return path, read_json(path)


def alternate_commands(args: argparse.Namespace, name: str, run: Callable[[str, str], dict]) -> dict:
    """``run(solver, key)`` for each solver of ``args``, alternating ``args.rounds`` times; results kept in ``<out>/<name>``
    as they come (a rerun skips the keys it has)."""
    path, results = results_file(args, name)
    for round_ in range(args.rounds):
        for solver in args.solvers:
            key = f"{getattr(args, 'label', None) or args.config}/{solver}/{round_}"
            if key not in results:
                results[key] = run(solver, key)
                path.write_text(json.dumps(results, indent=1))
    print(f"speed_benchmark: wrote {path}")
    return results


def timed_command(command: list[str], **options) -> dict:
    start = time.perf_counter()
    subprocess.run(command, check=True, **options)
    return {"wall_s": time.perf_counter() - start, "command": " ".join(command[1:])}


def run_fit(args: argparse.Namespace) -> None:
    from otgb.command import logger_override
    from otgb.runs import asks_for_gpu, machine

    out = Path(args.out)
    gpu = asks_for_gpu(args.overrides)

    def fit(solver: str, key: str) -> dict:
        env = None
        if args.cold_cache:  # an empty compile cache: what a new machine pays
            env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": tempfile.mkdtemp(prefix="otgb-inductor-")}
        return {"cold_cache": args.cold_cache, "threads": torch.get_num_threads(), "machine": machine(gpu)} | timed_command([
            sys.executable, "-m", "otgb.cli", "fit", "--config", str(ROOT / "configs" / f"{args.config}.yaml"),
            f"--solver={solver}", logger_override(str(out / "runs" / key), "run"), "--trainer.enable_progress_bar=false",
            f"--data.cache_dir={out / 'cache'}", *args.overrides,
        ], env=env)  # fmt: skip

    results = alternate_commands(args, "fit.json", fit)
    for solver in args.solvers:
        walls = [v["wall_s"] for k, v in results.items() if k.startswith(f"{args.label or args.config}/{solver}/")]
        runs = ", ".join(f"{w:.0f} s" for w in walls)
        print(f"{args.label or args.config} {solver:12s} whole fit {statistics.median(walls) / 60:6.2f} min (runs: {runs})")


def run_discover(args: argparse.Namespace) -> None:
    def discover(solver: str, key: str) -> dict:
        folder = Path(args.out) / "discover" / key  # the run writes runs/<config>/version_N in its working folder
        folder.mkdir(parents=True, exist_ok=True)
        command = [
            sys.executable, "-m", "otgb.cli", "discover", "--config", str(ROOT / "configs" / f"{args.config}.yaml"),
            "--data.hidden_effect=[]", f"--data.measured_path={Path(args.measured).resolve()}", f"--solver={solver}",
            "--trainer.enable_progress_bar=false", "--discover.fit_cache=null", *args.overrides,
        ]  # fmt: skip
        # no fit cache: a timed run fits everything, also when a stopped benchmark runs a key again
        with open(folder / "discover.log", "w") as log:
            result = timed_command(command, cwd=folder, stdout=log, stderr=subprocess.STDOUT)
        report = json.loads(next(folder.rglob("report.json")).read_text())
        terms = {f"{t['feature']} on d{t['component']}/dt": t["coefficient"] for t in report["terms"]}
        return {"wall_s": result["wall_s"], "terms": terms, "command": result["command"]}

    for key, value in alternate_commands(args, "discover.json", discover).items():
        terms = ", ".join(f"{name} {c:.5g}" for name, c in value["terms"].items()) or "nothing"
        print(f"discover {key:28s} {value['wall_s'] / 60:6.2f} min  {terms}")


def solve_designs(field, x0: torch.Tensor, args: Callable, substeps: int, n_intervals: int, h: float, block: int) -> dict:
    """Solve functions (no argument, returning (B, n_intervals + 1, *state)) for each design of ``designs``; the
    compiled step and the compiled loop are otgb's own (:mod:`otgb.physics.solvers`)."""
    from torchdiffeq import odeint

    from otgb.physics import solvers

    n_steps = n_intervals * substeps

    def looped(step):
        return lambda: solvers.stepwise_solve(field, x0, args(), "rk4", h, substeps, n_intervals, step=step)

    def steps_in_block(field, y, h, args):
        states = []
        for _ in range(block):
            y = solvers.STEPS["rk4"](field, y, h, args)
            states.append(y)
        return torch.stack(states, 1)

    compiled_block = torch.compile(steps_in_block, dynamic=True, fullgraph=True)

    def blocked():
        states, y = [x0[:, None]], x0
        for _ in range(n_steps // block):
            part = compiled_block(field, y, h, args())
            states.append(part)
            y = part[:, -1]
        return torch.cat(states, 1)[:, ::substeps]

    times, step = torch.arange(n_intervals + 1, dtype=torch.float32) * h * substeps, {"step_size": h}
    device = x0.device.type
    python_loop = torch.compile(solvers.whole_solve, dynamic=True, fullgraph=True)
    compiled_loop = solvers.compiled_whole_solve(device)
    return {
        "torchdiffeq": lambda: odeint(lambda _, y: field(y, *args()), x0, times, method="rk4", options=step).movedim(0, 1),
        "eager loop": looped(solvers.STEPS["rk4"]),
        "compiled step, Python wrapper": looped(torch.compile(solvers.STEPS["rk4"], dynamic=True, fullgraph=True)),
        "compiled step": looped(solvers.compiled_step("rk4", device)),
        f"compiled block of {block} steps": blocked,
        "compiled scan, Python wrapper": lambda: python_loop(field, x0, args(), "rk4", h, substeps, n_intervals),
        "compiled scan": lambda: compiled_loop(field, x0, args(), "rk4", h, substeps, n_intervals),
    } | (cuda_graph_designs(field, x0, args, substeps, n_intervals, h) if device == "cuda" else {})


def cuda_graph_designs(field, x0: torch.Tensor, args: Callable, substeps: int, n_intervals: int, h: float) -> dict:
    """The compiled scan replayed as a CUDA graph (``torch.compile``'s ``reduce-overhead``); on a GPU otgb's compiled
    step (``compiled step``) is replayed so already."""
    from otgb.physics import solvers

    loop = torch.compile(solvers.whole_solve, mode="reduce-overhead", dynamic=True, fullgraph=True)
    return {"compiled scan, CUDA graphs": lambda: loop(field, x0, args(), "rk4", h, substeps, n_intervals)}


def run_designs(args: argparse.Namespace) -> None:
    from otgb.runs import load_run, machine

    path, results = results_file(args, "designs.json")
    run = load_run(str(ROOT / "configs" / f"{args.config}.yaml"), "--trainer.logger=false")
    device = torch.device(args.device)
    greybox, physics = run.model.transport_map.to(device), run.model.physics.to(device)
    g = torch.Generator().manual_seed(0)
    batch = run.datamodule.batch_size
    x0, theta = physics.sample_initial_state(batch, g).to(device), physics.sample_theta(batch, g).to(device)
    cond = torch.cat([theta, torch.randn(batch, greybox.z_dim, generator=g).to(device)], 1)
    n_intervals = physics.n_obs - 1 if physics.include_initial else physics.n_obs
    substeps = round(physics.dt / physics.step_size)
    if hasattr(greybox.correction, "condition"):  # as GreyBoxODE.solve: the condition's share once per solve
        field, field_args = greybox.conditioned_field, lambda: (theta, *greybox.correction.condition(cond))
    else:
        field, field_args = greybox.vector_field, lambda: (theta, cond)
    designs = solve_designs(field, x0, field_args, substeps, n_intervals, physics.step_size, args.block)
    reference = designs["eager loop"]().detach()
    label = f"{args.config}-{args.label}" if args.label else args.config

    def timed_solve(solve: Callable) -> float:
        torch.compiler.cudagraph_mark_step_begin()  # a new iteration for the CUDA-graph designs; nothing elsewhere
        start = time.perf_counter()
        solve().square().sum().backward()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return time.perf_counter() - start

    for name, solve in designs.items():
        key = f"{label}/{name}"
        if key in results or (args.only and not any(word in name for word in args.only)):
            continue
        first = timed_solve(solve)
        each = [timed_solve(solve) for _ in range(args.repeats)]
        torch.compiler.cudagraph_mark_step_begin()
        difference = float((solve().detach() - reference).abs().max())
        median_ms, threads = 1000 * statistics.median(each), torch.get_num_threads()
        results[key] = {"median_ms": median_ms, "first_s": first, "max_difference": difference, "threads": threads}
        results[key]["machine"] = machine(device.type == "cuda")
        path.write_text(json.dumps(results, indent=1))
    eager = results[f"{label}/eager loop"]["median_ms"]
    threads = torch.get_num_threads()
    steps = n_intervals * substeps
    print(f"{label}: one grey-box solve + backward, batch {batch}, {steps} RK4 steps (torch threads {threads}, {device}):")
    for key, value in results.items():
        if key.startswith(f"{label}/"):
            print(
                f"  {key.split('/', 1)[1]:28s} {value['median_ms']:7.1f} ms  x{eager / value['median_ms']:4.2f} of eager  "
                f"first call {value['first_s']:6.1f} s  max |difference| {value['max_difference']:.1e}"
            )
    print(f"speed_benchmark: wrote {path}")


class LibraryConvNet(PaperConvNet):
    """The paper's judge network on ``torch.nn.Conv1d``'s own forward: the reference of ``judges``."""

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        return torch.nn.Sequential.forward(self, rows.unsqueeze(1)).squeeze(1)

    def fused(self, rows: torch.Tensor, parameters: tuple[torch.Tensor, ...]) -> bool:
        return False  # its training steps on autograd too, also where the fused loops could run (float32 on a CPU)


class LibraryConvJudge(PaperConvClassifier):
    def autocast(self, device: torch.device) -> torch.autocast:
        """ "auto" as for otgb's other judges (PaperConvClassifier's base), not float32 for the fused loops."""
        return super(PaperConvClassifier, self).autocast(device)

    def network(self, n_features: int) -> torch.nn.Module:
        return LibraryConvNet(n_features)


class TorchOpsNet(PaperConvNet):
    """The paper's judge network on otgb's torch operations (its path on a GPU or without numba), not the fused loops."""

    forward = PaperConvNet.torch_forward
    fused = LibraryConvNet.fused


class TorchOpsJudge(PaperConvClassifier):
    autocast = LibraryConvJudge.autocast

    def network(self, n_features: int) -> torch.nn.Module:
        return TorchOpsNet(n_features)


def judge_rows(rows: int, features: int, apart: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian rows, the second sample 2 % off in mean and 5 % in scale, or (``apart``) shifted by a sine of amplitude 1."""
    g = torch.Generator().manual_seed(0)
    p = torch.randn(rows // 2, features, generator=g)
    q = torch.randn(rows - rows // 2, features, generator=g)
    q = q + torch.sin(torch.arange(features) / 7.0) if apart else q * 1.05 + 0.02
    return torch.cat([p, q]).numpy(), np.r_[np.zeros(len(p)), np.ones(len(q))].astype(np.int64)


def split_rows(rows: np.ndarray, labels: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.as_tensor(rows[labels == 0]), torch.as_tensor(rows[labels == 1])


def advdiff_mm_test_rows(out: Path) -> tuple[torch.Tensor, torch.Tensor, tuple[int, ...]]:
    """The Adv-diff-m-m test set's joint rows as ``otgb test`` scores f_p alone: the process's draws, and f_p's
    trajectory of each input in their place; the folds keep each input's rows together, as there."""
    from otgb.metrics import joint_samples
    from otgb.runs import load_run

    config = str(ROOT / "configs" / "advdiff_mm.yaml")
    data_module = load_run(config, "--trainer.logger=false", f"--data.cache_dir={out / 'cache'}").datamodule
    data = data_module.source.evaluation_set("test", data_module.n_test)
    f_p = data["x"].unsqueeze(1).expand_as(data["y"])
    rows = [joint_samples(data["theta"], data["x0"], y) for y in (data["y"], f_p)]
    return rows[0], rows[1], tuple(data["y"].shape[2:])


def run_stopping(args: argparse.Namespace, path: Path, results: dict) -> None:
    """One fold of close rows and one of rows the judge separates, each trained with no tolerance on its held-out loss
    (up to ``--stop-cap`` epochs) and with its own."""
    from otgb.runs import machine

    for kind, apart in (("close", False), ("separable", True)):
        features, labels = judge_rows(args.rows, args.features, apart)
        order = np.random.default_rng(0).permutation(len(labels))
        train, test = order[: len(labels) * 4 // 5], order[len(labels) * 4 // 5 :]
        for tol, cap in ((0.0, args.stop_cap), (PaperConvClassifier().tol, PaperConvClassifier().max_epochs)):
            key = f"stopping/{kind}/tol {tol:g}"
            if key not in results:
                estimator = PaperConvClassifier(tol=tol, max_epochs=cap, precision=args.precision)
                start = time.perf_counter()
                estimator.fit(features[train], labels[train])
                wall = time.perf_counter() - start
                accuracy = float((estimator.predict(features[test]) == labels[test]).mean())
                results[key] = {"epochs": estimator.n_iter_, "max_epochs": cap, "wall_s": wall, "accuracy": accuracy}
                results[key] |= {"rows": list(features.shape), "machine": machine()}
                path.write_text(json.dumps(results, indent=1))


def run_judges(args: argparse.Namespace) -> None:
    from otgb.metrics.c2st import c2st
    from otgb.runs import machine

    path, results = results_file(args, "judges.json")
    features, labels = judge_rows(args.rows, args.features)
    fold = np.random.default_rng(0).permutation(len(labels))[: len(labels) * 4 // 5]  # one fold's training rows
    judges = {"library-conv1d": LibraryConvJudge, "torch-ops": TorchOpsJudge, "otgb": PaperConvClassifier}
    p, q = (torch.as_tensor(features[labels == c]) for c in (0, 1))
    fold_jobs = {"5 folds in turn": 1, "5 folds in threads": None}
    for round_ in range(args.rounds):
        for name, judge in judges.items():
            key = f"paper/{name}/{round_}"
            if key not in results:
                estimator = judge(max_epochs=args.epochs, n_iter_no_change=args.epochs, precision=args.precision)
                start = time.perf_counter()
                estimator.fit(features[fold], labels[fold])
                results[key] = {"s_per_epoch": (time.perf_counter() - start) / estimator.n_iter_, "rows": list(features.shape)}
                results[key]["machine"] = machine()
                path.write_text(json.dumps(results, indent=1))
        for name, jobs in fold_jobs.items():
            key = f"paper/{name}/{round_}"
            if key not in results:
                estimator = PaperConvClassifier(max_epochs=args.epochs, n_iter_no_change=args.epochs, precision=args.precision)
                start = time.perf_counter()
                c2st(p, q, folds=5, classifier=estimator, n_jobs=jobs)
                results[key] = {"s_per_epoch": (time.perf_counter() - start) / (5 * args.epochs), "rows": list(features.shape)}
                results[key]["machine"] = machine()
                path.write_text(json.dumps(results, indent=1))
    if args.stopping:
        run_stopping(args, path, results)
    cases = {
        "paper/otgb/c2st-apart": lambda: (*split_rows(*judge_rows(args.rows, args.features, apart=True)), None),
        "paper/otgb/c2st": lambda: (*split_rows(*judge_rows(args.rows, args.features)), None),
        "paper/otgb/c2st-advdiff-mm": lambda: advdiff_mm_test_rows(Path(args.out)),
    }
    for key, samples in cases.items():
        if args.whole and key not in results:
            p, q, trajectory_shape = samples()
            start = time.perf_counter()
            score = c2st(p, q, classifier="paper", trajectory_shape=trajectory_shape, precision=args.precision)
            wall = time.perf_counter() - start
            rows = [len(p) + len(q), p.shape[1]]
            results[key] = {"wall_s": wall, "c2st": float(score["c2st"]), "rows": rows, "machine": machine()}
            path.write_text(json.dumps(results, indent=1))
    for name in [*judges, *fold_jobs]:
        each = [v["s_per_epoch"] for k, v in results.items() if k.startswith(f"paper/{name}/") and "s_per_epoch" in v]
        print(f"paper judge, {name:15s} {statistics.median(each):6.3f} s per epoch (runs: {', '.join(f'{e:.3f}' for e in each)})")
    for key, run in results.items():
        if key.startswith("stopping/"):
            tried = f"{run['epochs']} epochs of {run['max_epochs']}, {run['wall_s']:.0f} s, accuracy {run['accuracy']:.4f}"
            print(f"paper judge, {key[9:].replace('/', ' rows, ')}: {tried} (one fold)")
        if key.startswith("paper/otgb/c2st"):
            rows = {"paper/otgb/c2st-apart": "separable rows", "paper/otgb/c2st": "close rows"}.get(key, key[11:] + " rows")
            print(f"paper judge, whole 5-fold C2ST, {rows}: {run['wall_s'] / 60:.1f} min (C2ST {run['c2st']:.3f})")
    print(f"speed_benchmark: wrote {path}")


LOCAL_MACHINE = "2-core x86_64 VM, torch 2.13.0+cpu"  # the machine of the step timings recorded before they named theirs
SECTION_START, SECTION_END = "<!-- speed: scripts/speed_benchmark.py -->", "<!-- end speed -->"


def write_table(args: argparse.Namespace) -> None:
    out, doc = Path(args.out), Path(args.doc)
    if not doc.is_file():
        raise SystemExit(f"speed_benchmark table: --doc {doc}: no such page")
    lines = [""]
    steps = read_json(out / "steps.json")
    configs = list(dict.fromkeys(key.split("/")[0] for key in steps))
    columns = ["config", "solver", "ms per training step", "speed-up", "first run's warm-up (s)", "runs", "torch threads"]
    lines += header([*columns, "machine"]) if configs else []
    for config in configs:
        solvers = list(dict.fromkeys(key.split("/")[1] for key in steps if key.startswith(f"{config}/")))
        reference = _median(steps, f"{config}/{solvers[0]}/", "median_ms")
        for solver in solvers:
            prefix = f"{config}/{solver}/"
            step, warmup = _median(steps, prefix, "median_ms"), _median(steps, prefix, "warmup_s")
            runs = [v for k, v in steps.items() if k.startswith(prefix)]
            threads = ", ".join(sorted({str(v["threads"]) for v in runs}))
            machines = ", ".join(sorted({v.get("machine", LOCAL_MACHINE) for v in runs}))
            figures = [f"{step:.1f}", f"{reference / step:.2f}x", f"{warmup:.1f}"]
            lines.append(row([config, solver, *figures, len(runs), threads, machines]))
    if fits := read_json(out / "fit.json"):
        lines += ["", *header(["whole `otgb fit`", "solver", "minutes", "runs", "compile cache", "torch threads", "machine"])]
        for prefix in dict.fromkeys(key.rsplit("/", 1)[0] + "/" for key in fits):
            config, solver = prefix.split("/")[:2]
            runs = [v for k, v in fits.items() if k.startswith(prefix)]
            walls = [v["wall_s"] / 60 for v in runs]
            caches = {"empty" if v.get("cold_cache") else "as found" if "cold_cache" in v else "-" for v in runs}
            cache = ", ".join(sorted(caches))
            threads = ", ".join(sorted({str(v.get("threads", "-")) for v in runs}))
            machines = ", ".join(sorted({v.get("machine", LOCAL_MACHINE) for v in runs}))
            lines.append(row([config, solver, f"{statistics.median(walls):.2f}", len(walls), cache, threads, machines]))
    lines += designs_table(out) + judges_table(out) + discover_table(out)
    write_between(doc, SECTION_START, SECTION_END, "\n".join(lines))
    print(f"speed_benchmark: wrote {doc}")


def designs_table(out: Path) -> list[str]:
    designs = read_json(out / "designs.json")
    if not designs:
        return []
    columns = ["grey-box solve + backward", "design", "ms", "of eager", "first call (s)", "max difference to eager"]
    lines = ["", *header([*columns, "torch threads"])]
    for key, value in designs.items():
        config, design = key.split("/", 1)
        ms, eager = value["median_ms"], designs[f"{config}/eager loop"]["median_ms"]
        cells = [f"{ms:.1f}", f"{eager / ms:.2f}x", f"{value['first_s']:.1f}", f"{value['max_difference']:.1e}", value["threads"]]
        lines.append(row([config, design, *cells]))
    return lines


def judges_table(out: Path) -> list[str]:
    judges = read_json(out / "judges.json")
    if not judges:
        return []
    columns = ["paper C2ST judge", "network, or how the folds train", "s per epoch of one fold", "of the library's", "runs"]
    lines = ["", *header([*columns, "machine"])]
    names = dict.fromkeys(key.split("/")[1] for key, run in judges.items() if "s_per_epoch" in run)
    runs_of = {name: [v for k, v in judges.items() if k.startswith(f"paper/{name}/") and "s_per_epoch" in v] for name in names}
    epoch = {name: statistics.median(v["s_per_epoch"] for v in runs) for name, runs in runs_of.items()}
    for name, runs in runs_of.items():
        rows, machines = " x ".join(map(str, runs[0]["rows"])), ", ".join(sorted({v.get("machine", LOCAL_MACHINE) for v in runs}))
        one_fold = "library-conv1d" in epoch and not name.startswith("5 folds")  # a whole C2ST's fold-epochs: no ratio
        ratio = f"{epoch['library-conv1d'] / epoch[name]:.2f}x" if one_fold else "-"
        lines.append(row([f"{rows} rows", name, f"{epoch[name]:.3f}", ratio, len(runs), machines]))
    kinds = {
        "c2st-apart": "separable rows,",
        "c2st": "close rows,",
        "c2st-advdiff-mm": "rows of the Adv-diff-m-m test set, f_p against the process,",
    }
    for name, kind in kinds.items():
        if f"paper/otgb/{name}" in judges:
            whole = judges[f"paper/otgb/{name}"]
            rows = " x ".join(map(str, whole["rows"]))
            lines.append(
                f"| {rows} {kind} whole 5-fold C2ST | otgb | {whole['wall_s'] / 60:.2f} min in all "
                f"(C2ST {whole['c2st']:.3f}) | - | 1 | {whole.get('machine', LOCAL_MACHINE)} |"
            )
    stops = {key[9:].replace("/", " rows, "): run for key, run in judges.items() if key.startswith("stopping/")}
    if stops:
        columns = ["paper judge, one fold: rows, tolerance", "epochs run (of at most)", "s", "accuracy, the fold's test rows"]
        lines += ["", *header([*columns, "machine"])]
        for name, r in stops.items():
            epochs, wall = f"{r['epochs']} ({r['max_epochs']})", f"{r['wall_s']:.0f}"
            lines.append(row([name, epochs, wall, f"{r['accuracy']:.4f}", r["machine"]]))
    return lines


def discover_table(out: Path) -> list[str]:
    runs = read_json(out / "discover.json")
    if not runs:
        return []
    lines = ["", *header(["whole `otgb discover`", "solver", "minutes", "named"])]
    for key, value in runs.items():
        config, solver, _ = key.split("/")
        named = "; ".join(f"`{name}` {c:.5g}" for name, c in value["terms"].items()) or "nothing"
        lines.append(row([config, solver, f"{value['wall_s'] / 60:.2f}", named]))
    return lines


def _median(results: dict, prefix: str, field: str) -> float:
    """The median of ``field`` over the runs under ``prefix``; for the warm-up, the first run's (the one that compiled)."""
    values = [v[field] for k, v in results.items() if k.startswith(prefix)]
    return values[0] if field == "warmup_s" else statistics.median(values)


CONFIG_NAMES = sorted(path.stem for path in (ROOT / "configs").glob("*.yaml"))  # --config takes a name, not a path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    steps = commands.add_parser("steps", help="training steps of each config, per solver")
    steps.add_argument("--configs", nargs="+", default=["pendulum", "advdiff", "reactdiff"], choices=CONFIG_NAMES)
    steps.add_argument("--steps", type=int, default=40)
    steps.add_argument("--warmup", type=int, default=5, help="first steps counted as warm-up (compilation)")
    steps.add_argument("--label", help="appended to each config's name in the results, for runs with overrides (e.g. gpu)")
    steps.add_argument("overrides", nargs="*", help="otgb overrides, after -- (e.g. --trainer.accelerator=gpu)")
    fit = commands.add_parser("fit", help="whole `otgb fit` commands, per solver")
    fit.add_argument("--config", default="reactdiff", choices=CONFIG_NAMES)
    fit.add_argument("--label", help="the results' name for this config and these overrides (default: the config)")
    fit.add_argument("--cold-cache", action="store_true", help="each fit compiles into an empty torch compile cache")
    fit.add_argument("overrides", nargs="*", help="otgb overrides, after --")
    judges = commands.add_parser("judges", help="the paper's C2ST judge: otgb's convolution against torch.nn.Conv1d")
    judges.add_argument("--rows", type=int, default=6000)
    judges.add_argument("--features", type=int, default=1041)
    judges.add_argument("--epochs", type=int, default=5, help="epochs per timed fit")
    judges.add_argument("--rounds", type=int, default=2)
    judges.add_argument("--precision", default="auto", help="the judge's arithmetic (otgb.metrics.classifiers)")
    judges.add_argument("--whole", action=argparse.BooleanOptionalAction, default=True, help="also whole 5-fold C2STs")
    judges.add_argument("--stopping", action=argparse.BooleanOptionalAction, default=True, help="also the stopping rule")
    judges.add_argument("--stop-cap", type=int, default=400, help="most epochs of the fold trained with no tolerance")
    designs = commands.add_parser("designs", help="ways of compiling a solve, on a config's grey-box")
    designs.add_argument("--config", default="pendulum", choices=CONFIG_NAMES)
    designs.add_argument("--block", type=int, default=7, help="steps per compiled block (divides the solve's steps)")
    designs.add_argument("--repeats", type=int, default=20)
    designs.add_argument("--only", nargs="*", help="run only the designs whose name has one of these words (e.g. eager scan)")
    designs.add_argument("--device", default="cpu", help="where the solves run (cpu, cuda: adds the CUDA-graph designs)")
    designs.add_argument("--label", help="appended to the config's name in the results (e.g. gpu)")
    discover = commands.add_parser("discover", help="whole `otgb discover` runs on a measured file, per solver")
    discover.add_argument("--config", default="pendulum", choices=CONFIG_NAMES)
    discover.add_argument("--measured", required=True, help="the measured file")
    discover.add_argument("overrides", nargs="*", help="otgb overrides, after --")
    for sub in (steps, fit, discover):
        sub.add_argument("--solvers", nargs="+", default=["torchdiffeq", "compiled"], help="the reference first")
        sub.add_argument("--rounds", type=int, default=2, help="alternations of the solvers")
    table = commands.add_parser("table", help="write the figures of --out into --doc")
    table.add_argument("--doc", required=True)
    for sub in (steps, fit, judges, designs, discover, table):
        sub.add_argument("--out", required=True)
    args = parser.parse_args()
    commands = {"steps": run_steps, "fit": run_fit, "judges": run_judges, "designs": run_designs, "discover": run_discover}
    {**commands, "table": write_table}[args.command](args)


if __name__ == "__main__":
    main()
