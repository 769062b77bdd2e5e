"""Guarded numerics: NaN/Inf updates are skipped and counted; a diverged training stops with a diagnosis and its state on disk."""

import csv

import torch
from test_cli import _args, _otgb, main

from otgb.guard import UpdateGuard


def test_a_failed_solve_skips_one_update_and_training_goes_on(tmp_path):
    poison = '--trainer.callbacks+={"class_path": "conftest.PoisonSources", "init_args": {"step": 2, "k": 1}}'
    main(["fit", *_args(tmp_path, "--trainer.max_steps=6", "--model.t_max=3", poison)])
    run = tmp_path / "run" / "version_0"
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    assert last["global_step"] == 6 and last["otgb"]["map_updates"] == 6 * 3 - 1, "one map update skipped, the step counted"
    moments = [s["exp_avg"] for s in last["optimizer_states"][0]["state"].values()]
    assert all(torch.isfinite(m).all() for m in moments), "the skipped update left Adam's moments clean"
    with open(run / "metrics.csv") as f:
        skipped = [float(r["train/skipped_steps"]) for r in csv.DictReader(f) if r.get("train/skipped_steps")]
    assert skipped[0] == 0.0 and skipped[-1] == 1.0


def test_a_diverging_training_stops_with_a_diagnosis_and_its_last_good_state(tmp_path):
    done = _otgb(tmp_path, "fit", *_args(tmp_path, "--trainer.max_steps=40", "--model.map_optimizer.init_args.lr=1000"))
    assert done.returncode == 1
    message = done.stderr.strip().splitlines()[-1]
    assert message.startswith("otgb: error: training diverged: ") and "NaN/Inf" in message
    in_training = "update(s) in a row gave NaN/Inf, the last one of the map" in message
    assert in_training or "the map's solve gave NaN/Inf on the validation inputs" in message, message
    assert "learning rates: map " in message and "model.map_optimizer.init_args.lr" in message
    run = tmp_path / "run" / "version_0"
    assert (run / "metrics.csv").exists()
    if "--ckpt_path" in message:  # stopped in training: the state it saved is the last good one
        last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
        assert all(torch.isfinite(v).all() for v in last["state_dict"].values() if v.is_floating_point())


def test_the_guard_counts_runs_of_skips():
    guard = UpdateGuard(limit=3)
    assert not guard.failed("map", "NaN") and not guard.failed("map", "NaN")
    guard.passed()
    assert not guard.failed("critic", "NaN") and not guard.failed("critic", "NaN") and guard.failed("critic", "Inf")
    assert guard.skipped == 5 and "critic learning rate" in guard.message({"map": 1e-4, "critic": 1e-4}, None)


def test_sigterm_saves_the_state_between_two_steps_and_the_run_resumes(tmp_path):
    term = '--trainer.callbacks+={"class_path": "conftest.SendSigterm", "init_args": {"step": 4}}'
    done = _otgb(tmp_path, "fit", *_args(tmp_path, "--trainer.max_steps=6", term))
    assert done.returncode == 143
    last = tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt"
    assert f"stopped by SIGTERM after step 4; resume with --ckpt_path {last}" in done.stderr
    assert torch.load(last, weights_only=False)["global_step"] == 4
    with open(last.parent.parent / "metrics.csv") as f:
        assert max(float(r["step"]) for r in csv.DictReader(f)) == 3.0, "every row up to the saved state (4 steps: 0-3)"
    resumed = _otgb(tmp_path, "fit", *_args(tmp_path, "--trainer.max_steps=6"), f"--ckpt_path={last}")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert torch.load(tmp_path / "run" / "version_1" / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == 6
