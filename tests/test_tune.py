"""`otgb tune` through the real command: real fits per trial, a persistent study, SIGTERM and resume, two workers,
a measured file, and bad input refused in one line."""

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from otgb.cli import main
from otgb.data import generate_measured
from otgb.physics import Constant, Pendulum, ViscousFriction
from otgb.tune import GRACE_S

ROOT = Path(__file__).parents[1]
CONFIG = str(ROOT / "configs" / "pendulum.yaml")
SPACE = "model.map_optimizer.init_args.lr: {log_uniform: [1.0e-4, 3.0e-3]}\ndata.batch_size: {choice: [16, 32]}\n"


def _tiny(tmp_path: Path, steps: int = 6) -> list[str]:
    return [
        "--trainer.enable_progress_bar=false", f"--trainer.max_steps={steps}", "--trainer.val_check_interval=3",
        "--data.simulation_budget=6400", "--data.n_measured=64", "--data.n_val=24", "--data.n_test=20",
        "--evaluation.reference_repeats=1", "--evaluation.c2st_folds=2", "--evaluation.mmdagg_permutations=200",
        "--components.enabled=false", f"--data.cache_dir={tmp_path / 'cache'}",
    ]  # fmt: skip


def _tune(tmp_path: Path, *args: str, wait: bool = True, space: str = SPACE):
    (tmp_path / "space.yaml").write_text(space)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "otgb.cli", "tune", "--config", CONFIG, "--tune.space=space.yaml", *args]
    if not wait:
        return subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)


def _tune_here(tmp_path: Path, monkeypatch, capsys, *args: str, space: str = SPACE) -> tuple[int, str, str]:
    """``otgb tune`` in this process (no interpreter start-up): (exit status, stdout, stderr)."""
    (tmp_path / "space.yaml").write_text(space)
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    try:
        main(["tune", "--config", CONFIG, "--tune.space=space.yaml", *args])
        code = 0
    except SystemExit as exit_info:
        code = exit_info.code
    out = capsys.readouterr()
    return code, out.out, out.err


def _trials(study_dir: Path) -> list[tuple]:
    """(number, state, params as text) of every trial in the study's SQLite file."""
    with sqlite3.connect(study_dir / "study.db") as db:
        rows = db.execute("SELECT trial_id, number, state FROM trials ORDER BY number").fetchall()
        params = {
            trial: tuple(sorted(db.execute("SELECT param_name, param_value FROM trial_params WHERE trial_id=?", (trial,))))
            for trial, _, _ in rows
        }
    return [(number, state, params[trial]) for trial, number, state in rows]


def test_a_study_runs_real_fits_writes_its_results_and_a_config_fit_takes(tmp_path, monkeypatch, capsys):
    code, out, err = _tune_here(tmp_path, monkeypatch, capsys, "--tune.trials=3", *_tiny(tmp_path))
    assert code == 0, err[-2000:]
    study = tmp_path / "runs" / "tune-pendulum"
    last = out.strip().splitlines()[-1]
    assert last.startswith("otgb tune: best of 3 completed trials: trial ") and " val/abs_err " in last, last
    assert {"trials.md", "best.yaml", "history.png", "importances.png", "study.db"} <= {p.name for p in study.iterdir()}
    assert sorted(p.name for p in study.glob("trial_*")) == ["trial_0000", "trial_0001", "trial_0002"]
    for trial in study.glob("trial_*"):
        assert (trial / "version_0" / "config.yaml").is_file() and (trial / "version_0" / "checkpoints" / "last.ckpt").is_file()
    table = (study / "trials.md").read_text()
    assert table.count("| complete |") == 3 and "val/abs_err, lower is better" in table
    first = next(line for line in table.splitlines() if line.startswith("| 0 |"))
    assert "| 0.001 | 32 |" in first and "the config's own settings" in first, "trial 0 runs where the config starts"
    assert table.count("the config's own settings") == 1
    best = yaml.safe_load((study / "best.yaml").read_text())
    lr = best["model"]["map_optimizer"]["init_args"]["lr"]
    assert f"{lr:.4g}" in last, "best.yaml holds the best trial's settings"
    main(["fit", "--config", str(study / "best.yaml"), "--trainer.max_steps=2"])
    assert (tmp_path / "runs" / "tune-pendulum-best" / "version_0" / "checkpoints" / "last.ckpt").is_file()
    code, _, _ = _tune_here(tmp_path, monkeypatch, capsys, "--tune.trials=3", *_tiny(tmp_path))
    assert code == 0 and len(_trials(study)) == 3, "the study is complete: the same command adds nothing"
    _budget_sweep_records(tmp_path, study)


def _budget_sweep_records(tmp_path: Path, study: Path) -> None:
    """scripts/budget_sweep.py's `study` copies a finished study's files and summary, and `table` lists it."""
    script = [sys.executable, str(ROOT / "scripts" / "budget_sweep.py")]
    storage = f"sqlite:///{study / 'study.db'}"
    record = [*script, "study", "--out", str(tmp_path / "out"), "--name", "s", "--storage", storage, "--study", "pendulum"]
    subprocess.run([*record, "--space", "space.yaml"], check=True, capture_output=True)
    summary = json.loads((tmp_path / "out" / "s" / "study.json").read_text())
    assert summary["trials"] == 3 and summary["states"] == {"complete": 3} and summary["monitor"] == "val/abs_err"
    assert summary["first_value"] >= summary["best_value"] and {p.name for p in (tmp_path / "out" / "s").iterdir()} == {
        "study.json",
        "trials.md",
        "best.yaml",
        "history.png",
        "importances.png",
    }
    (tmp_path / "out" / "sweep.json").write_text(json.dumps({"64/16/seed0": {
        "budget": 64, "batch": 16, "seed": 0, "overrides": [], "fit_s": 1.0, "model_abs_err": 0.5, "fp_abs_err": 0.4,
        "map_lr": 1e-3, "critic_lr": 1e-3, "machine": "m"}}))  # fmt: skip
    shown = subprocess.run([*script, "table", "--out", str(tmp_path / "out")], check=True, capture_output=True, text=True)
    line = shown.stdout.strip().splitlines()[-1]
    assert line.startswith("- `otgb tune` study `pendulum` over `space.yaml`") and f"{summary['best_value']:.4g}" in line


def _worker_in_its_second_trial(tmp_path: Path, steps: int) -> subprocess.Popen:
    """A worker of a 2-trial study, once its second trial has begun logging."""
    worker = _tune(tmp_path, "--tune.trials=2", "--tune.pruner=none", *_tiny(tmp_path, steps=steps), wait=False)
    second = tmp_path / "runs" / "tune-pendulum" / "trial_0001" / "version_0" / "metrics.csv"
    deadline = time.time() + 600
    while not second.exists() and worker.poll() is None and time.time() < deadline:
        time.sleep(0.5)
    return worker


@pytest.mark.slow
def test_sigterm_stops_a_trial_and_the_same_command_finishes_the_study_without_losing_or_repeating(tmp_path):
    worker = _worker_in_its_second_trial(tmp_path, steps=18)
    worker.send_signal(signal.SIGTERM)
    worker.wait(timeout=300)
    assert worker.returncode == 128 + signal.SIGTERM, worker.stderr.read()[-2000:]
    stopped = _trials(tmp_path / "runs" / "tune-pendulum")
    assert [s for _, s, _ in stopped] == ["COMPLETE", "FAIL", "WAITING"], stopped
    done = _tune(tmp_path, "--tune.trials=2", "--tune.pruner=none", *_tiny(tmp_path, steps=18))
    assert done.returncode == 0, done.stderr[-2000:]
    trials = _trials(tmp_path / "runs" / "tune-pendulum")
    complete = [params for _, state, params in trials if state == "COMPLETE"]
    assert len(trials) == 3 and len(complete) == 2 and len(set(complete)) == 2, trials
    assert stopped[1][2] == trials[2][2] and trials[2][1] == "COMPLETE", "the interrupted trial ran again, once"


@pytest.mark.slow
def test_two_workers_share_one_study_and_never_run_a_trial_twice(tmp_path):
    workers = [_tune(tmp_path, "--tune.trials=4", "--tune.pruner=none", *_tiny(tmp_path), wait=False) for _ in range(2)]
    for worker in workers:
        worker.wait(timeout=900)
        assert worker.returncode == 0, worker.stderr.read()[-2000:]
    trials = _trials(tmp_path / "runs" / "tune-pendulum")
    assert [s for _, s, _ in trials].count("COMPLETE") >= 4
    folders = sorted(p.name for p in (tmp_path / "runs" / "tune-pendulum").glob("trial_*"))
    assert folders == [f"trial_{n:04d}" for n, _, _ in trials], "one run directory per trial number: none ran twice"


def test_a_study_on_a_measured_file_selects_on_the_marginal_metric(tmp_path, monkeypatch, capsys):
    y = generate_measured(Pendulum().with_hidden_effect([ViscousFriction(Constant(1.2))]), 120, 3)["y"]
    np.savez(tmp_path / "measured.npz", y=y.numpy())
    measured = f"--data.measured_path={tmp_path / 'measured.npz'}"
    args = ["--tune.trials=2", *_tiny(tmp_path), "--data.hidden_effect=[]", measured]
    code, out, err = _tune_here(tmp_path, monkeypatch, capsys, *args, space="data.batch_size: {choice: [16, 32]}\n")
    assert code == 0, err[-2000:]
    assert " val/energy " in out.strip().splitlines()[-1]
    assert "val/energy, lower is better" in (tmp_path / "runs" / "tune-pendulum" / "trials.md").read_text()


@pytest.mark.parametrize(
    "space, args, expected",
    [
        (
            "model.map_optimizer.init_args.lrr: {uniform: [0.1, 0.2]}\n",
            [],
            "not a setting of this config (did you mean model.map_",
        ),
        ("model.t_max: {int: [4, 2]}\n", [], "the range [4, 2] is empty or invalid"),
        ("data.batch_size: {choice: []}\n", [], "choice needs a non-empty list"),
        ("data.batch_size: {choice: [16]}\n", ["--tune.storage=sqlite:////nonexistent/dir/x.db"], "cannot be opened"),
        ("data.batch_size: {choice: [16]}\n", ["--tune.trials=0"], "tune.trials=0: expected >= 1"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_nothing_written(tmp_path, monkeypatch, capsys, space, args, expected):
    (tmp_path / "space.yaml").write_text(space)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(["tune", "--config", CONFIG, "--tune.space=space.yaml", *args, *_tiny(tmp_path)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and lines[-1].startswith("otgb: error: ") and expected in lines[-1], lines[-3:]
    assert not (tmp_path / "runs").exists(), "nothing written"


def test_a_study_name_taken_by_another_space_is_refused(tmp_path, monkeypatch, capsys):
    code, out, _ = _tune_here(tmp_path, monkeypatch, capsys, "--tune.trials=1", *_tiny(tmp_path))
    before = sorted(p.name for p in (tmp_path / "runs" / "tune-pendulum").iterdir())
    assert code == 0 and "history.png" in before and "importances.png" not in before, before
    assert "importances.png" not in out, "the closing line names only the files written"
    space = "data.batch_size: {choice: [16, 64]}\n"
    code, _, err = _tune_here(tmp_path, monkeypatch, capsys, "--tune.trials=1", *_tiny(tmp_path), space=space)
    assert code == 2 and "was started with another space" in err.strip().splitlines()[-1]
    assert sorted(p.name for p in (tmp_path / "runs" / "tune-pendulum").iterdir()) == before, "nothing written"


@pytest.mark.slow
def test_a_killed_worker_s_trial_is_retried_once_its_heartbeat_is_stale(tmp_path):
    worker = _worker_in_its_second_trial(tmp_path, steps=30)
    worker.kill()
    worker.wait()
    time.sleep(GRACE_S + 10)
    done = _tune(tmp_path, "--tune.trials=2", "--tune.pruner=none", *_tiny(tmp_path, steps=30))
    assert done.returncode == 0, done.stderr[-2000:]
    trials = _trials(tmp_path / "runs" / "tune-pendulum")
    assert [s for _, s, _ in trials] == ["COMPLETE", "FAIL", "COMPLETE"], trials
    assert trials[1][2] == trials[2][2], "the killed trial's settings ran again"


def test_a_sampled_value_the_parser_rejects_fails_that_trial_not_the_study(tmp_path, monkeypatch, capsys):
    space = "data.batch_size: {choice: [16, not-a-number]}\n"
    code, out, err = _tune_here(
        tmp_path, monkeypatch, capsys, "--tune.trials=3", "--tune.sampler=random", *_tiny(tmp_path), space=space
    )
    assert code == 0, err[-2000:]
    table = (tmp_path / "runs" / "tune-pendulum" / "trials.md").read_text()
    assert table.count("| complete |") + table.count("| fail |") == 3, table
    assert "| fail |" in table and "the config parser rejected these settings" in table, "seeded: trials 0 and 1 draw it"
