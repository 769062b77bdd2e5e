"""Real 2-process CPU runs under Lightning's DDP (gloo), each killed with all its processes past a hard timeout."""

import csv
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from otgb.command import logger_override

ROOT = Path(__file__).parents[1]
DDP = ["--trainer.strategy=ddp", "--trainer.devices=2", "--trainer.accelerator=cpu"]
LIGHTNING = [sys.executable]  # Lightning starts the second process itself
TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2"]  # `torchrun`
TIMEOUT_S = 300


def _otgb_ddp(cwd: Path, *args: str, launcher: list[str] = LIGHTNING, returncode: int = 0) -> subprocess.CompletedProcess:
    """``python -m otgb.cli ...`` on 2 processes; a run still going after TIMEOUT_S (a hang) is killed and fails the test."""
    path = os.pathsep.join([str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])
    command = [*launcher, "-m", "otgb.cli", *args, *DDP]
    run = subprocess.Popen(
        command, cwd=cwd, env={**os.environ, "PYTHONPATH": path}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,  # Lightning starts the second process as a child: kill the whole group
    )  # fmt: skip
    try:
        out, err = run.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(run.pid, signal.SIGKILL)
        out, err = run.communicate()
        pytest.fail(f"{' '.join(args[:3])}: no end after {TIMEOUT_S} s under DDP (a hang); stderr ends:\n{err[-2000:]}")
    assert run.returncode == returncode, err[-3000:]
    assert "sync_dist" not in err and "Traceback" not in err, err[-3000:]
    return subprocess.CompletedProcess(command, run.returncode, out, err)


def _args(tmp_path: Path, config: str, *extra: str) -> list[str]:
    return [
        "--config", str(ROOT / "configs" / config), logger_override(str(tmp_path), "run"),
        "--trainer.enable_progress_bar=false", f"--data.cache_dir={tmp_path / 'cache'}",
        "--data.n_measured=64", "--data.n_val=24", "--data.n_test=20", "--evaluation.reference_repeats=2",
        *extra,
    ]  # fmt: skip


def test_two_process_fit_and_test_of_the_pendulum(tmp_path):
    record = f'--trainer.callbacks+={{"class_path": "conftest.RecordSources", "init_args": {{"folder": "{tmp_path}"}}}}'
    steps = ["--data.simulation_budget=640", "--data.batch_size=16", "--model.t_max=2", "--trainer.val_check_interval=5"]
    _otgb_ddp(tmp_path, "fit", *_args(tmp_path, "pendulum.yaml", *steps, record))
    run = tmp_path / "run" / "version_0"
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    assert last["global_step"] == 10, "640 simulations / (2 processes x 2 updates x 16 sources) = 10 steps"
    assert last["SimulationDataModule"]["items_consumed"] == 10
    sources = [torch.load(tmp_path / f"sources_rank{r}.pt") for r in (0, 1)]
    assert all(len(s) == 320 for s in sources), "each process simulates half of the budget"
    assert not (sources[0][:, None] == sources[1][None]).all(-1).any(), "the processes draw disjoint source streams"
    with open(run / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["step"]) for r in rows if r.get("val/abs_err")] == [4.0, 9.0], "one process writes the log, once"
    assert sorted(p.name for p in (run / "figures").iterdir())[-1] == "trajectories_step0000010.png"

    odd = [*_args(tmp_path, "pendulum.yaml"), "--data.n_test=21", f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"]
    _otgb_ddp(tmp_path, "test", *odd, "--data.eval_batch_size=5")  # 21 inputs: 11 (3 batches) and 10 (2), none twice
    subprocess.run([sys.executable, "-m", "otgb.cli", "test", *odd], cwd=tmp_path, check=True, capture_output=True)
    both, one = (json.loads((tmp_path / "run" / f"version_{v}" / "metrics.json").read_text()) for v in (1, 2))
    assert both["run"]["global_step"] == 10 and both["model"]["abs_err"]["mean"] > 0
    assert both["model"]["abs_err"]["mean"] == pytest.approx(one["model"]["abs_err"]["mean"], rel=1e-5), "as one process"


@pytest.mark.slow  # the pendulum's two-process run above covers DDP in the default suite
def test_two_process_fit_and_test_of_advection_diffusion(tmp_path):
    steps = ["--data.simulation_budget=256", "--data.batch_size=16", "--model.t_max=2", "--trainer.val_check_interval=4"]
    _otgb_ddp(tmp_path, "fit", *_args(tmp_path, "advdiff.yaml", *steps))
    last = tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False)["global_step"] == 4
    _otgb_ddp(tmp_path, "test", *_args(tmp_path, "advdiff.yaml"), f"--ckpt_path={last}")
    assert json.loads((tmp_path / "run" / "version_1" / "metrics.json").read_text())["model"]["abs_err"]["mean"] > 0


@pytest.mark.slow
def test_a_resumed_two_process_run_matches_an_uninterrupted_one(tmp_path):
    steps = ["--data.simulation_budget=640", "--data.batch_size=16", "--model.t_max=2", "--trainer.val_check_interval=5"]
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    _otgb_ddp(tmp_path / "a", "fit", *_args(tmp_path / "a", "pendulum.yaml", *steps))
    stop = '--trainer.callbacks+={"class_path": "conftest.StopAt", "init_args": {"step": 5}}'
    _otgb_ddp(tmp_path / "b", "fit", *_args(tmp_path / "b", "pendulum.yaml", *steps, stop))
    last = tmp_path / "b" / "run" / "version_0" / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False)["global_step"] == 5
    _otgb_ddp(tmp_path / "b", "fit", *_args(tmp_path / "b", "pendulum.yaml", *steps), f"--ckpt_path={last}")
    full = torch.load(tmp_path / "a" / "run" / "version_0" / "checkpoints" / "last.ckpt", weights_only=False)
    resumed = torch.load(tmp_path / "b" / "run" / "version_1" / "checkpoints" / "last.ckpt", weights_only=False)
    assert resumed["global_step"] == full["global_step"] == 10
    for name, value in full["state_dict"].items():
        assert torch.allclose(value, resumed["state_dict"][name], atol=1e-6), name


@pytest.mark.slow
def test_torchrun_starts_the_same_two_process_run(tmp_path):
    steps = ["--data.simulation_budget=640", "--data.batch_size=16", "--model.t_max=2", "--trainer.val_check_interval=5"]
    for folder, launcher in (("lightning", LIGHTNING), ("torchrun", TORCHRUN)):
        (tmp_path / folder).mkdir()
        _otgb_ddp(tmp_path / folder, "fit", *_args(tmp_path / folder, "pendulum.yaml", *steps), launcher=launcher)
    spawned, started = (torch.load(tmp_path / f / "run" / "version_0" / "checkpoints" / "last.ckpt", weights_only=False)
                        for f in ("lightning", "torchrun"))  # fmt: skip
    assert started["global_step"] == spawned["global_step"] == 10
    for name, value in spawned["state_dict"].items():
        assert torch.allclose(value, started["state_dict"][name], atol=1e-6), name
    folder = tmp_path / "torchrun"
    last = folder / "run" / "version_0" / "checkpoints" / "last.ckpt"
    _otgb_ddp(folder, "test", *_args(folder, "pendulum.yaml"), f"--ckpt_path={last}", launcher=TORCHRUN)
    assert json.loads((folder / "run" / "version_1" / "metrics.json").read_text())["run"]["global_step"] == 10


@pytest.mark.slow
def test_sigterm_to_one_process_stops_both_after_the_same_step_and_resumes(tmp_path):
    steps = ["--data.simulation_budget=640", "--data.batch_size=16", "--model.t_max=2", "--trainer.val_check_interval=5"]
    term = '--trainer.callbacks+={"class_path": "conftest.SendSigterm", "init_args": {"step": 3, "rank": 1}}'
    done = _otgb_ddp(tmp_path, "fit", *_args(tmp_path, "pendulum.yaml", *steps, term), returncode=143)
    last = tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt"
    assert f"stopped by SIGTERM after step 3; resume with --ckpt_path {last}" in done.stderr
    assert torch.load(last, weights_only=False)["global_step"] == 3, "saved by both processes after the step rank 1 was signalled"
    _otgb_ddp(tmp_path, "fit", *_args(tmp_path, "pendulum.yaml", *steps), f"--ckpt_path={last}")
    assert torch.load(tmp_path / "run" / "version_1" / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == 10


@pytest.mark.slow
def test_two_process_fit_on_the_compiled_path_follows_the_reference_path(tmp_path):
    """Each DDP process compiles its own steps (from the shared on-disk cache) and trains as on torchdiffeq's path."""
    steps = ["--data.simulation_budget=1280", "--data.batch_size=16", "--trainer.val_check_interval=20"]
    scores = {}
    for solver in ("torchdiffeq", "compiled"):
        (tmp_path / solver).mkdir()
        _otgb_ddp(tmp_path / solver, "fit", *_args(tmp_path / solver, "pendulum.yaml", *steps, f"--solver={solver}"))
        with open(tmp_path / solver / "run" / "version_0" / "metrics.csv") as f:
            scores[solver] = [float(r["val/abs_err"]) for r in csv.DictReader(f) if r.get("val/abs_err")]
    assert len(scores["compiled"]) == len(scores["torchdiffeq"]) == 2
    assert torch.allclose(torch.tensor(scores["compiled"]), torch.tensor(scores["torchdiffeq"]), rtol=2e-3)
