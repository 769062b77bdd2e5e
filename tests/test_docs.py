"""docs/own-physics.md and docs/own-data.md done as written: files in a fresh folder, commands as real subprocesses.

The document's files are its fenced blocks with a title (```python title="my_oscillator.py"),
its commands the lines of its ```bash blocks, run in order from that folder. What the test
changes, and only that: ``otgb`` is ``python -m otgb.cli`` with this checkout first on the path,
``/path/to/otgb`` is this checkout, and every ``otgb`` command gets the overrides in ``TINY``.
"""

import ast
import csv
import importlib.util
import json
import math
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

ROOT = Path(__file__).parents[1]
_SPEC = importlib.util.spec_from_file_location("walkthroughs", ROOT / "scripts" / "walkthroughs.py")
walkthroughs = importlib.util.module_from_spec(_SPEC)  # the pages' files, commands and how a shell runs them
_SPEC.loader.exec_module(walkthroughs)

DOC = ROOT / "docs" / "own-physics.md"
OWN_DATA = ROOT / "docs" / "own-data.md"
LAB_DATA = ROOT / "docs" / "lab-data.md"
DISCOVER_TINY = ["--discover.n_permutations=199", "--discover.n_trajectories=48", "--discover.n_bootstrap=5"]
DISCOVER_TINY += ["--discover.fit_steps=30", "--discover.fit_batch=256", "--discover.strong_candidates=1"]
TINY = [  # a seconds-long run of the same config: 6 steps, validation at 3 and 6, small sets
    "--trainer.enable_progress_bar=false",
    "--trainer.max_steps=6",
    "--trainer.val_check_interval=3",
    "--trainer.log_every_n_steps=1",
    "--data.batch_size=16",
    "--data.n_measured=64",
    "--data.n_val=24",
    "--data.n_test=20",
    "--evaluation.reference_repeats=1",
    "--evaluation.c2st_folds=2",
    "--evaluation.mmdagg_permutations=200",
]


def _run(command: str, cwd: Path) -> subprocess.CompletedProcess:
    """One documented command line, as a shell would run it in ``cwd``, at the tests' size (see the module docstring)."""
    return walkthroughs.run(command, cwd, TINY, env={"OMP_NUM_THREADS": "1"})


def _written(tmp_path: Path, text: str, **edits: str) -> dict[str, str]:
    files = walkthroughs.files(text)
    assert sorted(files) == ["my_oscillator.py", "oscillator.yaml"]
    for name, content in files.items():
        (tmp_path / name).write_text(edits.get(name, content))
    return files


def _rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv") as handle:
        return list(csv.DictReader(handle))


def test_the_documented_oscillator_trains_and_tests_from_the_users_folder(tmp_path):
    text = DOC.read_text()
    _written(tmp_path, text)
    commands = walkthroughs.commands(text)
    assert [shlex.split(c)[1:3] for c in commands] == [
        ["otgb", "fit"],
        ["otgb", "test"],
        ["python", "/path/to/otgb/scripts/export_measured.py"],
        ["otgb", "fit"],
        ["otgb", "test"],
    ]
    for command in commands:
        done = _run(command, tmp_path)
        assert done.returncode == 0, f"{command}\n{done.stderr[-3000:]}"

    runs = tmp_path / "runs" / "oscillator"
    fit = runs / "version_0"
    assert {"metrics.csv", "config.yaml", "hparams.yaml"} <= {p.name for p in fit.iterdir()}
    assert list(fit.glob("events.out.tfevents.*")) and (fit / "checkpoints" / "last.ckpt").is_file()
    assert len(list(fit.glob("checkpoints/best-step=*.ckpt"))) == 1
    figures = sorted(p.name for p in (fit / "figures").iterdir())
    assert figures == ["components.png", "trajectories_step0000003.png", "trajectories_step0000006.png"]
    rows = _rows(fit)
    assert [float(r["val/fp_abs_err"]) for r in rows if r.get("val/fp_abs_err")][0] > 0.05, "f_p misses the friction"
    assert len([r for r in rows if r.get("val/abs_err")]) == 2
    cached = sorted(p.name.split("-")[0] for p in (tmp_path / "data").iterdir())
    assert cached == ["baselines"] * 4 + ["measured", "test", "val"], "the sets, and f_p and the Reference on each (2 runs x 2)"

    report = json.loads((runs / "version_1" / "metrics.json").read_text())
    assert report["fp"]["abs_err"]["mean"] > 0.05 and report["reference"]["abs_err"]["mean"] == 0.0
    assert report["model"]["abs_err"]["mean"] > 0 and report["run"]["n_inputs"] == 20
    table = (runs / "version_1" / "metrics.md").read_text()
    assert "| metric | better | model | f_p alone | Reference |" in table and "| ABS ERR | lower |" in table

    exported = (tmp_path / "measurements.csv").read_text().splitlines()
    assert len(exported) == 1 + 200 * 40
    assert exported[:3] == walkthroughs.blocks(text, "text")[0].splitlines(), "the CSV begins as the document shows"
    marginal = runs / "version_2"
    assert yaml.safe_load((marginal / "config.yaml").read_text())["checkpoint"]["monitor"] == "val/joint_energy"
    assert len([r for r in _rows(marginal) if r.get("val/joint_energy")]) == 2
    assert len(list(marginal.glob("checkpoints/best-step=*.ckpt"))) == 1
    report = json.loads((runs / "version_3" / "metrics.json").read_text())
    assert report["run"]["n_inputs"] == 30, "30 of the 200 trajectories held out for the test"
    assert "**marginal**" in (runs / "version_3" / "metrics.md").read_text()


def test_the_documented_errors_are_what_a_run_prints(tmp_path):
    text = DOC.read_text()
    section = text[text.index("## When a declaration is wrong") :]
    observed_error, prior_error = walkthroughs.blocks(section, "text")[:2]
    fit = walkthroughs.commands(text)[0]
    module = walkthroughs.files(text)["my_oscillator.py"]

    wrong_name = module.replace('observed = ("position",)', 'observed = ("x",)')
    assert wrong_name != module and 'With `observed = ("x",)` in `my_oscillator.py`' in section
    _written(tmp_path, text, **{"my_oscillator.py": wrong_name})
    done = _run(fit, tmp_path)
    assert done.returncode == 2 and done.stderr.rstrip().endswith(observed_error), done.stderr[-2000:]

    no_velocity = re.sub(r"\n *velocity: Prior = .*", "", module)
    assert no_velocity != module and "Without the `velocity` argument in `__init__`" in section
    (tmp_path / "my_oscillator.py").write_text(no_velocity)
    done = _run(fit, tmp_path)
    assert done.returncode == 2 and done.stderr.rstrip().splitlines()[-1] == prior_error, done.stderr[-2000:]
    assert not (tmp_path / "runs").exists()


def test_the_stated_line_counts_are_true():
    text = DOC.read_text()
    files = walkthroughs.files(text)
    module = files["my_oscillator.py"]
    code = {i for i, line in enumerate(module.splitlines(), 1) if line.strip() and not line.strip().startswith("#")}
    docstrings = set()
    for node in ast.walk(ast.parse(module)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef)) and ast.get_docstring(node) is not None:
            docstrings |= set(range(node.body[0].lineno, node.body[0].end_lineno + 1))
    config = files["oscillator.yaml"].splitlines()
    config_code = [line for line in config if line.strip() and not line.strip().startswith("#")]
    stated = " ".join(text[text.index("## Size") :].split())
    assert f"`my_oscillator.py`: {len(code)} lines that are neither blank nor comments" in stated
    assert f"({len(code - docstrings)} without the docstrings)" in stated
    assert f"`oscillator.yaml`: {len(config_code)} such lines, {len(config)} in all" in stated
    assert len(config) <= 25


def test_own_data_walkthrough_as_written(tmp_path):
    """docs/own-data.md: the stand-in CSV, the config, fit and test, the log line, the report, a bad file."""
    text = OWN_DATA.read_text()
    files = walkthroughs.files(text)
    assert sorted(files) == ["my_pendulum.yaml"]
    (tmp_path / "my_pendulum.yaml").write_text(files["my_pendulum.yaml"])
    commands = walkthroughs.commands(text)
    assert [shlex.split(c)[:2] for c in commands] == [
        ["python", "/path/to/otgb/scripts/export_measured.py"],
        ["otgb", "fit"],
        ["otgb", "test"],
    ]
    outputs = []
    for command in commands:
        done = _run(command, tmp_path)
        assert done.returncode == 0, f"{command}\n{done.stderr[-3000:]}"
        outputs.append(done.stderr)
    csv_head, log_line, recorded_head, error_line = walkthroughs.blocks(text, "text")
    table = text[text.index("<!-- results: scripts/walkthroughs.py test-3 -->") :]
    assert (tmp_path / "measurements.csv").read_text().splitlines()[:3] == csv_head.splitlines()
    assert log_line in outputs[1].splitlines(), "the fit names the mode as the document shows"
    fit = tmp_path / "runs" / "my_pendulum" / "version_0"
    assert next(fit.glob("figures/distributions_step*.png")) and (fit / "checkpoints" / "last.ckpt").is_file()
    report = (tmp_path / "runs" / "my_pendulum" / "version_1" / "metrics.md").read_text()
    labels = lambda t: [line.split(" | ")[0] for line in t.splitlines() if line.startswith("| ")]  # noqa: E731
    assert labels(table[table.index("| metric |") :].split("\n\n")[0]) == labels(
        report[report.index("| metric |") :].split("\n\n")[0]
    )

    exported = tmp_path / "recorded.csv"
    export = [sys.executable, str(ROOT / "scripts" / "export_measured.py"), "--config", str(ROOT / "configs" / "pendulum.yaml")]
    subprocess.run([*export, "--out", str(exported), "--record", "theta", "x0"], check=True, capture_output=True)
    assert exported.read_text().splitlines()[:2] == recorded_head.splitlines()

    (tmp_path / "bad.csv").write_text("trajectory,t,angle\n0,0,0.1\n0,0.2,0.1\n")
    before = sorted(p.name for p in (tmp_path / "runs" / "my_pendulum").iterdir())
    done = _run("otgb fit --config my_pendulum.yaml --data.measured_path bad.csv", tmp_path)
    assert done.returncode == 2 and done.stderr.strip().splitlines()[-1] == error_line
    assert sorted(p.name for p in (tmp_path / "runs" / "my_pendulum").iterdir()) == before, "nothing written"


def _filmed(tmp_path: Path) -> list[str]:
    """docs/lab-data.md's script run as written (200 runs filmed, not 1000) in ``tmp_path``, its file checked: runs
    that stop at their own times, lost frames left out or empty; the page's commands."""
    text = LAB_DATA.read_text()
    files = walkthroughs.files(text)
    assert sorted(files) == ["film_pendulum.py"] and "for run in range(1000):" in files["film_pendulum.py"]
    (tmp_path / "film_pendulum.py").write_text(files["film_pendulum.py"].replace("range(1000)", "range(200)"))
    commands = walkthroughs.commands(text)
    assert [shlex.split(c)[:2] for c in commands] == [["python", "film_pendulum.py"], ["otgb", "fit"], ["otgb", "discover"]]
    assert _run(commands[0], tmp_path).returncode == 0
    with open(tmp_path / "lab.csv") as handle:
        rows = list(csv.DictReader(handle))
    lengths = {row["trajectory"]: float(row["t"]) for row in rows}  # each run's last time
    assert len(lengths) == 200 and len(set(lengths.values())) > 40, "each run stops at its own time"
    empty = sum(row["angle"] == "" for row in rows) / len(rows)
    assert 0.05 < empty < 0.15 and len(rows) < 0.95 * sum(round(t * 30) + 1 for t in lengths.values()), "lost frames"
    drives = [float(row["drive"]) for row in rows]
    assert all(math.isfinite(d) for d in drives) and np.std(drives) > 0.2, "every logged row records the drive"
    return commands


def test_lab_data_walkthrough_fits_as_written(tmp_path):
    """docs/lab-data.md: the SciPy script's file of driven runs at their own times with lost frames, fitted as written (at
    the tests' size): its drive reaches f_phi; the file is left as it was."""
    commands = _filmed(tmp_path)
    before = (tmp_path / "lab.csv").read_bytes()
    fit = _run(commands[1], tmp_path)
    assert fit.returncode == 0, fit.stderr[-3000:]
    energies = [float(r["val/energy"]) for r in _rows(tmp_path / "runs" / "pendulum" / "version_0") if r.get("val/energy")]
    assert energies and all(math.isfinite(e) for e in energies)
    state = torch.load(tmp_path / "runs" / "pendulum" / "version_0" / "checkpoints" / "last.ckpt", weights_only=False)
    first = state["state_dict"]["transport_map.correction.hidden.0.weight"]
    assert first.shape[1] == 3 + 16, "f_phi sees angle, velocity and the recorded drive"
    assert (tmp_path / "lab.csv").read_bytes() == before


@pytest.mark.slow
def test_lab_data_walkthrough_discovers_as_written(tmp_path):
    """docs/lab-data.md's `otgb discover` on the script's file (at the tests' size; about 4 minutes on 2 cores): f_p
    without friction differs from the filmed runs, and the report is written."""
    commands = _filmed(tmp_path)
    found = walkthroughs.run(commands[2], tmp_path, [*TINY, *DISCOVER_TINY], env={"OMP_NUM_THREADS": "1"})
    assert found.returncode == 0, found.stderr[-3000:]
    report = json.loads(next((tmp_path / "runs" / "pendulum").glob("version_*/report.json")).read_text())
    assert report["locate"]["before"]["significant_cells"] > 0, "f_p without friction differs from the filmed runs"


def test_the_pages_show_the_committed_walkthrough_results():
    """Every number the tutorials show from their own run is what scripts/walkthroughs.py writes from results/."""
    for page in ("own-data", "own-physics", "lab-data"):
        text = (ROOT / "docs" / f"{page}.md").read_text()
        shown = walkthroughs.sections(page)
        assert {"test-2", "test-3", "discover-3"} & set(shown), sorted(shown)
        for name, section in shown.items():
            start = f"<!-- results: scripts/walkthroughs.py {name} -->"
            if start in text:
                assert text.split(start, 1)[1].split(walkthroughs.END, 1)[0].strip() == section.strip(), (page, name)


def test_the_docs_site_builds_strict(tmp_path):
    """`mkdocs build --strict`: every page in the navigation exists, every link and API reference resolves."""
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, capture_output=True, text=True, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "site" / "api" / "index.html").read_text().count("MapTraining") > 0


def test_readme_is_a_front_door():
    """README stays short: what otgb is, set-up, the three commands, links; the rest is on the docs site."""
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 120
    for link in re.findall(r"\]\((docs/[^)]+)\)", readme):
        assert (ROOT / link).is_file(), link


def test_the_first_fit_tutorial_runs_as_written(tmp_path):
    """docs/first-fit.md's commands in a fresh folder (at the tests' tiny size): fit, test, print_config, an override."""
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    text = (ROOT / "docs" / "first-fit.md").read_text()
    commands = [c for c in walkthroughs.commands(text) if c.startswith("otgb ")]
    assert [c.split()[1] for c in commands] == ["fit", "test", "fit", "fit"], commands
    for command in commands:
        done = _run(command, tmp_path)
        assert done.returncode == 0, f"{command}\n{done.stderr[-2000:]}"
        if "--print_config" in command:
            assert "simulation_budget" in done.stdout
    runs = sorted(p.name for p in (tmp_path / "runs" / "pendulum").iterdir())
    assert runs == ["version_0", "version_1", "version_2"], runs
    assert (tmp_path / "runs" / "pendulum" / "version_1" / "metrics.md").is_file(), "otgb test wrote its report"


def test_the_load_run_example_tests_a_saved_run_into_a_new_version(tmp_path):
    """docs/runs.md's Python example on a run of the first-fit tutorial's command: the run it loads stays as it was."""
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    assert _run("otgb fit --config configs/pendulum.yaml", tmp_path).returncode == 0
    fitted = tmp_path / "runs" / "pendulum" / "version_0"
    kept = {path: path.read_bytes() for path in fitted.rglob("*") if path.is_file()}
    section = (ROOT / "docs" / "runs.md").read_text().split("## Load a run in Python", 1)[1]
    example = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    done = subprocess.run([sys.executable, "-c", example], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)})  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "runs" / "pendulum" / "version_1" / "metrics.md").is_file(), "the test's report, in a new version"
    assert {path: path.read_bytes() for path in kept} == kept
