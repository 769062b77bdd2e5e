"""metrics.json / metrics.md and the cross-seed table of scripts/gather_metrics.py."""

import json
import subprocess
import sys
from pathlib import Path

from otgb.reports import write_report

SCRIPT = Path(__file__).parents[1] / "scripts" / "gather_metrics.py"


def _write(run_dir: Path, name: str, c2st: float) -> None:
    results = {"mmd": 0.01, "c2st": c2st, "c2st_std": 0.02, "fp_c2st": 0.99, "fp_c2st_std": 0.0}
    results |= {"ref_c2st": 0.5, "ref_c2st_std": 0.01, "eval_seconds": 3.0}
    write_report(run_dir, {"name": name, "ckpt_path": "x.ckpt", "global_step": 7}, results)


def test_report_files(tmp_path):
    _write(tmp_path, "pendulum_mm", 0.7)
    content = json.loads((tmp_path / "metrics.json").read_text())
    assert content["model"]["c2st"] == {"mean": 0.7, "std": 0.02} and content["model"]["mmd"] == {"mean": 0.01, "std": None}
    assert content["reference"]["c2st"] == {"mean": 0.5, "std": 0.01} and "mmd" not in content["fp"]
    assert content["seconds"]["model"] == 3.0
    table = (tmp_path / "metrics.md").read_text()
    assert "| C2ST accuracy | 0.5: cannot be told apart; 1: always can | 0.7 ± 0.02 | 0.99 ± 0 | 0.5 ± 0.01 |" in table
    assert "C2ST accuracy: model 0.7, f_p alone 0.99, Reference (noise floor) 0.5 ± 0.01: the model closes 59% of f_p's" in table
    _write(tmp_path, "small_held_out_set", 0.28)  # below the Reference: noise of 30 held-out rows, not a share > 100 %
    assert (
        "model 0.28, f_p alone 0.99, Reference (noise floor) 0.5 ± 0.01: the model is at the noise floor"
        in (tmp_path / "metrics.md").read_text()
    )


def test_a_summary_says_when_the_model_is_no_closer_than_f_p_and_then_reads_the_next_metric(tmp_path):
    results = {"c2st": 0.9997, "fp_c2st": 0.998, "ref_c2st": 0.5, "energy": 0.0934, "fp_energy": 2.4, "ref_energy": 0.0}
    write_report(tmp_path, {"name": "saturated", "ckpt_path": "x.ckpt", "global_step": 7}, results)
    sentence = (tmp_path / "metrics.md").read_text().split("\n\n")[3]
    assert "C2ST accuracy: model 1, f_p alone 0.998, Reference (noise floor) 0.5: the model is no closer to the noise" in sentence
    assert sentence.endswith("Reference (noise floor) 0: the model closes 96% of f_p's distance to the noise floor.")
    assert "-0%" not in sentence


def test_a_summary_that_finds_f_p_at_the_floor_by_c2st_says_when_the_mmdagg_test_rejects_it(tmp_path):
    """30 held-out trajectories: the C2ST cannot tell f_p from them, the MMDAgg test can; the sentence says both."""
    results = {"c2st": 0.4667, "fp_c2st": 0.4667, "ref_c2st": 0.5533, "fp_mmdagg_reject": 1.0, "fp_mmdagg_pvalue": 0.005988}
    write_report(tmp_path, {"name": "few_held_out", "ckpt_path": "x.ckpt", "global_step": 7}, results)
    sentence = (tmp_path / "metrics.md").read_text().split("\n\n")[3]
    assert sentence == (
        "C2ST accuracy: model 0.467, f_p alone 0.467, Reference (noise floor) 0.553: by this metric f_p alone is already at "
        "the noise floor; yet the MMDAgg test tells f_p alone from the held-out data (adjusted p-value 0.006)."
    )
    write_report(tmp_path, {"name": "few_held_out", "ckpt_path": "x.ckpt", "global_step": 7}, results | {"fp_mmdagg_reject": 0.0})
    assert (tmp_path / "metrics.md").read_text().split("\n\n")[3].endswith("already at the noise floor.")


def test_gather_groups_seeds(tmp_path):
    for seed, c2st in enumerate([0.7, 0.8]):
        _write(tmp_path / f"s{seed}", f"pendulum_mm_seed{seed}", c2st)
    _write(tmp_path / "other", "pendulum_2m", 0.6)
    files = sorted(str(p) for p in tmp_path.glob("*/metrics.json"))
    out = subprocess.run(
        [sys.executable, str(SCRIPT), *files, "--metrics", "c2st", "--out", str(tmp_path / "table.md")],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "| pendulum_mm | 2 | 0.75 ± 0.071 | 0.99 ± 0 | 0.5 ± 0 |" in out
    assert "| pendulum_2m | 1 | 0.6 | 0.99 | 0.5 |" in out
    assert (tmp_path / "table.md").read_text() == out
    bad = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "missing.json")], capture_output=True, text=True)
    assert bad.returncode != 0 and "missing.json: cannot read" in bad.stderr
