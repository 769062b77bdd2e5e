"""The measured-data mode through the real `otgb` command: a file in, marginal scores and reports out."""

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from otgb.cli import main
from otgb.command import logger_override

ROOT = Path(__file__).parents[1]
CONFIG = str(ROOT / "configs" / "pendulum.yaml")


def export(tmp_path: Path, name: str, *record: str, n: int = 200, noise: float = 0.0) -> Path:
    """The friction pendulum's measurements written to a file by scripts/export_measured.py."""
    out = tmp_path / name
    script = str(ROOT / "scripts" / "export_measured.py")
    command = [sys.executable, script, "--config", CONFIG, "--out", str(out), "--n", str(n), "--record", *record]
    subprocess.run([*command, "--noise", str(noise)], check=True)
    return out


def marginal_args(tmp_path: Path, measured: Path, *extra: str) -> list[str]:
    return [
        "--config",
        CONFIG,
        logger_override(str(tmp_path), "run"),
        "--trainer.enable_progress_bar=false",
        "--trainer.val_check_interval=3",
        "--data.simulation_budget=3200",
        "--data.batch_size=16",
        "--data.hidden_effect=[]",
        f"--data.measured_path={measured}",
        "--evaluation.reference_repeats=2",
        "--evaluation.mmdagg_permutations=200",
        f"--data.cache_dir={tmp_path / 'cache'}",
        *extra,
    ]


def _rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "metrics.csv") as f:
        return list(csv.DictReader(f))


def test_fit_and_test_on_a_measured_file(tmp_path):
    measured = export(tmp_path, "friction.npz")
    before = measured.read_bytes()
    main(["fit", *marginal_args(tmp_path, measured, "--trainer.max_steps=6", "--evaluation.tests_every=2")])
    run = tmp_path / "run" / "version_0"
    rows = _rows(run)
    energies = {int(float(r["step"])) + 1: float(r["val/energy"]) for r in rows if r.get("val/energy")}
    assert sorted(energies) == [3, 6] and not any(r.get("val/abs_err") for r in rows), "nothing paired to score pointwise"
    assert next(run.glob("checkpoints/best-*.ckpt")).name == f"best-step={min(energies, key=energies.get)}.ckpt"
    assert "monitor: val/energy" in (run / "config.yaml").read_text(), "checkpoint.monitor auto -> the marginal energy"
    assert sorted(p.name for p in (run / "figures").iterdir()) == [
        "components.png",
        "distributions_step0000003.png",
        "distributions_step0000006.png",
    ]
    fp, ref, ref_std = (
        float(next(r[f"val/{k}"] for r in rows if r.get(f"val/{k}"))) for k in ("fp_energy", "ref_energy", "ref_energy_std")
    )
    assert fp > ref + 3 * ref_std, "f_p alone is far from the measurements, two halves of them are not"

    main(["test", *marginal_args(tmp_path, measured), f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"])
    report_dir = tmp_path / "run" / "version_1"
    report = json.loads((report_dir / "metrics.json").read_text())
    assert report["run"]["mode"] == "marginal" and report["run"]["measured_path"] == str(measured)
    assert report["run"]["split"] == {"train": 140, "val": 30, "test": 30} and report["run"]["n_inputs"] == 30
    assert {"mmd", "mmd2_median", "energy", "mmdagg_reject", "c2st"} <= set(report["fp"]) and "abs_err" not in report["model"]
    reference = report["reference"]["energy"]
    assert report["fp"]["energy"]["mean"] > reference["mean"] + 3 * reference["std"]
    per_time = report["per_time"]
    assert per_time["components"] == ["angle"] and len(per_time["times"]) == 50 and len(per_time["fp"]) == 50
    assert per_time["fp"][0][0] < 0.01 < per_time["fp"][-1][0], "f_p starts where the measurements start, then drifts"
    table = (report_dir / "metrics.md").read_text()
    assert "Evaluation mode **marginal**" in table and "two halves" in table and "| Energy distance" in table
    assert measured.read_bytes() == before, "the user's file is never modified"
    cached = {path.name.split("-")[0] for path in (tmp_path / "cache").iterdir()}
    assert cached == {"baselines"}, "no set is generated for a file; only f_p's and the Reference's scores are kept"
    assert "trained_on" not in report["run"] and "Note:" not in table


def test_a_checkpoint_tested_on_other_measurements_says_so_in_the_report_and_its_summary(tmp_path, capsys):
    measured = export(tmp_path, "friction.npz")
    main(["fit", *marginal_args(tmp_path, measured, "--trainer.max_steps=2", "--evaluation.tests_every=0")])
    joint = [a for a in marginal_args(tmp_path, tmp_path) if not a.startswith(("--data.hidden_effect", "--data.measured"))]
    main(["test", *joint, "--data.n_test=20", f"--ckpt_path={tmp_path / 'run' / 'version_0' / 'checkpoints' / 'last.ckpt'}"])
    report_dir = tmp_path / "run" / "version_1"
    trained_on = f"the measurements in {measured.resolve()}"
    assert json.loads((report_dir / "metrics.json").read_text())["run"]["trained_on"] == trained_on
    note = f"the checkpoint was trained on {trained_on}, not on these measurements"
    assert f"**Note: {note}.**" in (report_dir / "metrics.md").read_text()
    summary = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("otgb test:"))
    assert summary.endswith(f"({note}).")


def test_recorded_inputs_give_joint_metrics_on_real_data(tmp_path):
    measured = export(tmp_path, "friction.csv", "theta", "x0")
    main(["fit", *marginal_args(tmp_path, measured, "--trainer.max_steps=3", "--evaluation.tests_every=0")])
    run = tmp_path / "run" / "version_0"
    assert "monitor: val/joint_energy" in (run / "config.yaml").read_text()
    main(["test", *marginal_args(tmp_path, measured), f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"])
    report = json.loads((tmp_path / "run" / "version_1" / "metrics.json").read_text())
    assert report["run"]["recorded_inputs"] == ["theta", "x0"]
    model, fp = report["model"], report["fp"]
    assert {"joint_abs_err", "joint_nrmse", "joint_c2st", "joint_energy", "energy"} <= set(model)
    assert fp["joint_abs_err"]["mean"] > 0.1, "f_p alone on the recorded inputs misses the friction"
    assert "joint_abs_err" not in report["reference"], "no repeated measurement of one input: no pointwise floor"
    assert "joint with recorded inputs: ABS ERR" in (tmp_path / "run" / "version_1" / "metrics.md").read_text()
    assert (
        report["run"]["across_halves"]
        and "score the model and f_p across the Reference's splits" in (tmp_path / "run" / "version_1" / "metrics.md").read_text()
    ), "draws on the test part's own inputs never meet their own measurement"
    assert model["energy"]["std"] is not None and model["mmdagg_reject"]["std"] is not None, "over the splits"


@pytest.mark.parametrize(
    "content, message",
    [
        ({"y": np.zeros((200, 40, 1))}, r"'y': measured trajectories have shape \(200, 40, 1\), expected \(N, 50, 1\)"),
        ({"y": np.zeros((30, 50, 1))}, r"30 trajectories split .* 22 train / 4 validation / 4 test"),
        (
            {"y": np.zeros((200, 50, 1)), "t": np.arange(50) * 0.2},
            r"t=5 lies outside the model's horizon \[0, 4.9\] .* last until t=9.8; set data.physics.init_args.n_obs to 99",
        ),
    ],
)
def test_a_bad_file_is_one_line_before_anything_is_written(tmp_path, content, message):
    path = tmp_path / "bad.npz"
    np.savez(path, **content)
    command = [
        sys.executable,
        "-m",
        "otgb.cli",
        "fit",
        "--config",
        CONFIG,
        "--data.hidden_effect=[]",
        f"--data.measured_path={path}",
    ]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 2 and result.stderr.strip().splitlines() == [result.stderr.strip()]
    assert result.stderr.startswith(f"otgb: error: {path}") and re.search(message, result.stderr)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz"], "no run directory, no cache"


def test_a_cache_folder_that_cannot_be_written_costs_a_warning_not_the_results(tmp_path):
    measured = export(tmp_path, "friction.npz")
    (tmp_path / "a-file").write_text("not a folder")
    blocked = f"--data.cache_dir={tmp_path / 'a-file' / 'cache'}"  # under a file: no user, root included, can write there
    done = subprocess.run(
        [sys.executable, "-m", "otgb.cli", "test", *marginal_args(tmp_path, measured, blocked)], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "otgb: evaluation.cache_baselines: cannot write" in done.stderr and "scored again next run" in done.stderr
    report = json.loads((tmp_path / "run" / "version_0" / "metrics.json").read_text())
    assert report["fp"]["energy"]["mean"] > report["reference"]["energy"]["mean"], "the baselines are there all the same"


def test_a_perfect_model_of_noisy_measurements_is_at_the_floor_only_when_their_noise_is_given(tmp_path):
    """The DGP itself (complete physics) scored on 1000 measurements with white noise of sd 0.1: compared noise-free, its
    draws are told apart from the held-out measurements (the noise gives them away); with data.measurement_noise, the
    draws carry as much noise and every metric sits at the Reference's floor."""
    measured = export(tmp_path, "noisy.npz", n=1000, noise=0.1)
    xi = "{class_path: otgb.physics.Constant, init_args: {value: 1.2}}"
    effect = f"[{{class_path: otgb.physics.ViscousFriction, init_args: {{xi: {xi}}}}}]"
    complete = ["--model.transport_map=otgb.models.CompletePhysicsMap", f"--model.transport_map.init_args.hidden_effect={effect}"]
    reports = {}
    for sd in (0.0, 0.1):
        folder = tmp_path / f"sd{sd}"
        main(["test", *marginal_args(folder, measured, *complete, f"--data.measurement_noise={sd}")])
        reports[sd] = json.loads((folder / "run" / "version_0" / "metrics.json").read_text())
    floor = reports[0.1]["reference"]
    for report in reports.values():
        assert report["reference"] == floor, "the Reference compares the measurements with themselves: noise or not"
    c2st, energy = floor["c2st"], floor["energy"]
    assert reports[0.0]["model"]["c2st"]["mean"] > 0.8 and reports[0.0]["model"]["mmdagg_reject"]["mean"] == 1
    assert reports[0.1]["model"]["c2st"]["mean"] < c2st["mean"] + 2 * c2st["std"]
    assert reports[0.1]["model"]["energy"]["mean"] < energy["mean"] + 2 * energy["std"]
    assert reports[0.1]["model"]["mmdagg_reject"]["mean"] == 0
    assert reports[0.1]["run"]["measurement_noise"] == 0.1 and "white noise (sd 0.1)" in reports[0.1]["run"]["description"]
