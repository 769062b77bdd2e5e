"""otgb.runs.fit_and_test (the scripts' fit-then-test, resumable) and scripts/budget_sweep.py, on real seconds-long runs."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from otgb.runs import asks_for_gpu, fit_and_test

ROOT = Path(__file__).parents[1]
CONFIG = str(ROOT / "configs" / "pendulum.yaml")


def _tiny(cache: Path) -> list[str]:
    small = ["--trainer.val_check_interval=2", "--data.n_measured=24", "--data.n_val=12", "--data.n_test=12"]
    small += [f"--data.cache_dir={cache}", "--evaluation.reference_repeats=1", "--evaluation.c2st_folds=2"]
    return [*small, "--evaluation.mmdagg_permutations=200", "--components.enabled=false"]


@pytest.mark.slow
def test_fit_and_test_returns_a_finished_run_as_it_is_and_resumes_a_fit_from_its_last_checkpoint(tmp_path):
    args = ["--config", CONFIG, "--seed_everything=3", "--data.simulation_budget=64", "--data.batch_size=16", *_tiny(tmp_path)]
    first = fit_and_test(tmp_path / "run", args)
    assert math.isfinite(first["model"]["abs_err"]["mean"]) and first["fit_s"] > 0 and not first["resumed"]
    assert fit_and_test(tmp_path / "run", args) == first, "a run with a test report is not run again"
    assert len(list((tmp_path / "run" / "fit").glob("version_*"))) == 1

    for report in (tmp_path / "run" / "test").rglob("metrics.json"):
        report.unlink()  # as if the sweep had stopped between the fit and the test
    again = fit_and_test(tmp_path / "run", args)
    assert again["resumed"], "the fit continued from its last.ckpt"
    assert again["model"]["abs_err"] == first["model"]["abs_err"], "the same best checkpoint, tested again"


@pytest.mark.slow
def test_budget_sweep_spreads_each_budget_over_the_steps_and_writes_its_table_into_a_page(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Results\n\n<!-- results: scripts/budget_sweep.py -->\nSTALE TABLE\n<!-- end results -->\n\nafter\n")
    script = [sys.executable, str(ROOT / "scripts" / "budget_sweep.py")]
    run = [*script, "run", "--out", str(tmp_path / "out"), "--name", "tiny", "--config", CONFIG, "--budgets", "64", "128"]
    done = subprocess.run([*run, "--steps", "4", "--", *_tiny(tmp_path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    results = json.loads((tmp_path / "out" / "tiny.json").read_text())
    assert sorted((r["budget"], r["batch"]) for r in results.values()) == [(64, 16), (128, 32)]
    subprocess.run([*script, "table", "--out", str(tmp_path / "out"), "--doc", str(page)], check=True, capture_output=True)
    text = page.read_text()
    assert "STALE TABLE" not in text and text.endswith("<!-- end results -->\n\nafter\n")
    rows = [line.split(" | ") for line in text.splitlines() if line.startswith("| tiny |")]
    assert [(row[1], row[2]) for row in rows] == [("64", "16"), ("128", "32")]
    assert {row[3] for row in rows} == {"0.001 / 0.001"}, "the learning rates as trained, from the checkpoints"
    assert all(f"{r['model_abs_err']:.4g}" in text for r in results.values())


@pytest.mark.slow
def test_average_tests_the_mean_of_the_seeds_corrections_beside_each_seed(tmp_path):
    script = [sys.executable, str(ROOT / "scripts" / "budget_sweep.py")]
    run = [*script, "run", "--out", str(tmp_path), "--name", "tiny", "--config", CONFIG, "--budgets", "64", "128"]
    done = subprocess.run([*run, "--steps", "4", "--seeds", "0", "1", "--", *_tiny(tmp_path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    seeds = [tmp_path / "runs" / "tiny" / "64" / "16" / f"seed{s}" for s in (0, 1)]
    files_before = sorted(tmp_path.joinpath("runs").rglob("*"))
    average = [*script, "average", "--out", str(tmp_path), "--sweep", "tiny", "--folders"]
    done = subprocess.run([*average, *map(str, seeds)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(tmp_path.joinpath("runs").rglob("*")) == files_before, "nothing written into the runs"
    result = json.loads((tmp_path / "averaged" / "tiny-64-16.json").read_text())
    recorded = json.loads((tmp_path / "tiny.json").read_text())
    assert result["per_seed"] == pytest.approx([recorded[f"64/16/seed{s}"]["model_abs_err"] for s in (0, 1)], abs=1e-6)
    assert math.isfinite(result["averaged"]) and result["averaged"] not in result["per_seed"], "one map of both"
    table = subprocess.run([*script, "table", "--out", str(tmp_path)], capture_output=True, text=True, check=True).stdout
    assert f"mean of its 2 seeds' f_phi has test ABS ERR {result['averaged']:.4g}" in table

    gap = [*script, "gap", "--out", str(tmp_path), "--sweep", "tiny", "--inputs", "200", "--folders", *map(str, seeds)]
    subprocess.run(gap, capture_output=True, text=True, check=True)
    assert sorted(tmp_path.joinpath("runs").rglob("*")) == files_before, "nothing written into the runs"
    where = json.loads((tmp_path / "gap" / "tiny-64-16.json").read_text())
    # four steps leave each map at about f_p: it costs about nothing, so about the true map's cost less than the
    # truth, and its outputs sit far from the DGP's, beyond the noise of two DGP samples
    assert where["cost_minus_true"] == pytest.approx([-where["true_cost"]] * 2, rel=0.1)
    assert min(where["energy"]) > 5 * where["null_energy_sd"] > 0 and abs(where["true_energy"]) < 4 * where["null_energy_sd"]
    table = subprocess.run([*script, "table", "--out", str(tmp_path)], capture_output=True, text=True, check=True).stdout
    assert f"| tiny | 64 | 16 | seed1 | 200 | {where['abs_err'][1]:.4g} |" in table
    one_input = [*script, "gap", "--sweep", "tiny", "--inputs", "1", "--folders", str(seeds[0])]
    done = subprocess.run(one_input, capture_output=True, text=True)
    assert done.returncode == 1 and done.stderr.strip().endswith(
        "--inputs 1: expected at least 2 (a distance between samples needs two each)"
    )
    other = tmp_path / "runs" / "tiny" / "128" / "32" / "seed1"
    done = subprocess.run([*average, str(seeds[0]), str(other)], capture_output=True, text=True)
    assert done.returncode == 1 and "not seeds of one budget and batch of tiny" in done.stderr.splitlines()[-1]
    elsewhere = tmp_path / "elsewhere" / "64" / "16" / "seed1"  # a key of the sweep, but no fit there
    done = subprocess.run([*average, str(seeds[0]), str(elsewhere)], capture_output=True, text=True)
    assert done.returncode == 1 and len(done.stderr.splitlines()) == 1 and "no finished fit" in done.stderr, done.stderr


@pytest.mark.slow
@pytest.mark.parametrize(
    "kind, overrides, metric, expected",
    [
        ("wgan", ["--config", str(ROOT / "configs" / "baselines" / "wgan.yaml")], "abs_err", "which has no transport cost"),
        ("file", ["--data.hidden_effect=[]", "--data.measured_path={measured}"], "mmd", "no deterministic configured DGP"),
    ],
)
def test_gap_refuses_a_sweep_without_a_transport_cost_or_a_true_map_in_one_line(tmp_path, kind, overrides, metric, expected):
    measured = tmp_path / "measured.npz"
    np.savez(measured, y=np.zeros((120, 50, 1), dtype=np.float32) + np.linspace(0, 1, 120)[:, None, None])
    script = [sys.executable, str(ROOT / "scripts" / "budget_sweep.py")]
    run = [*script, "run", "--out", str(tmp_path), "--name", kind, "--config", CONFIG, "--budgets", "160", "--batches", "16"]
    extra = [override.format(measured=measured) for override in overrides]
    done = subprocess.run([*run, "--metric", metric, "--", *_tiny(tmp_path), *extra], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    seed = tmp_path / "runs" / kind / "160" / "16" / "seed0"  # the WGAN: 2 steps of 5 batches
    files_before = sorted(tmp_path.joinpath("runs").rglob("*"))
    gap = [*script, "gap", "--out", str(tmp_path), "--sweep", kind, "--inputs", "50", "--folders", str(seed)]
    done = subprocess.run(gap, capture_output=True, text=True)
    assert done.returncode == 1 and len(done.stderr.splitlines()) == 1 and expected in done.stderr, done.stderr
    assert sorted(tmp_path.joinpath("runs").rglob("*")) == files_before and not (tmp_path / "gap").exists()


def test_merge_joins_sweeps_run_side_by_side_into_one_and_removes_the_parts(tmp_path):
    parts = {"a": {"1024/32/seed0": {"budget": 1024}}, "b": {"1024/32/seed1": {"budget": 1024}}}
    for name, results in parts.items():
        (tmp_path / f"{name}.json").write_text(json.dumps(results))
    script = [sys.executable, str(ROOT / "scripts" / "budget_sweep.py"), "merge", "--out", str(tmp_path)]
    subprocess.run([*script, "--name", "joined", "--parts", "a", "b"], check=True, capture_output=True)
    assert json.loads((tmp_path / "joined.json").read_text()) == {**parts["a"], **parts["b"]}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["joined.json"]
    for parts, expected in ((["c"], "no result file for ['c']"), (["joined"], "joined.json exists")):
        done = subprocess.run([*script, "--name", "joined", "--parts", *parts], capture_output=True, text=True)
        assert done.returncode == 1 and expected in done.stderr and len(done.stderr.splitlines()) == 1, done.stderr
    (tmp_path / "d.json").write_text(json.dumps(parts_of_one := {"1024/32/seed0": {}}))
    (tmp_path / "e.json").write_text(json.dumps(parts_of_one))
    done = subprocess.run([*script, "--name", "de", "--parts", "d", "e"], capture_output=True, text=True)
    assert "e repeats runs ['1024/32/seed0']" in done.stderr and not (tmp_path / "de.json").exists()
    assert (tmp_path / "d.json").exists() and (tmp_path / "e.json").exists(), "the parts are kept"


def test_the_results_page_shows_the_committed_budget_sweeps():
    """docs/results.md's budget table is what scripts/budget_sweep.py writes from the committed results/budget/."""
    script = [sys.executable, str(ROOT / "scripts" / "budget_sweep.py"), "table", "--out", str(ROOT / "results" / "budget")]
    written = subprocess.run(script, capture_output=True, text=True, check=True).stdout
    page = (ROOT / "docs" / "results.md").read_text()
    shown = page.split("<!-- results: scripts/budget_sweep.py -->", 1)[1].split("<!-- end results -->", 1)[0]
    assert "| pendulum-3125-steps |" in shown and shown.strip() == written.strip()


def test_a_gpu_is_asked_for_in_either_form_of_the_accelerator_override():
    assert asks_for_gpu(["--trainer.accelerator=gpu"]) and asks_for_gpu(["--seed_everything=1", "--trainer.accelerator", "cuda"])
    assert not asks_for_gpu(["--trainer.accelerator=cpu", "--trainer.devices", "gpu"]) and not asks_for_gpu([])
