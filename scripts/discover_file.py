"""What the benchmarks on files from independent solvers share: ``otgb discover`` on one measured file in a case's
folder, seeded, timed, its report.json and report.md kept beside the case's summary (``runs/`` is not committed)::

    from discover_file import discover_file
    report, timing = discover_file(folder, "pendulum.yaml", "measured.csv", overrides, seed)
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

from otgb.runs import launch_otgb, machine, newest

ROOT = Path(__file__).parents[1]


def discover_file(folder: Path, config: str, measured: str, overrides: list[str], seed: int) -> tuple[dict | None, dict]:
    """The report of ``otgb discover`` on ``folder/measured`` with ``configs/config`` (None where it failed) and the
    run's wall time, exit status and machine."""
    args = ["discover", "--config", str(ROOT / "configs" / config), f"--data.measured_path={measured}", *overrides]
    args += [f"--seed_everything={seed}", f"--data.seed={seed}", f"--discover.seed={seed}"]
    args += ["--trainer.enable_progress_bar=false", "--discover.fit_cache=null"]  # timed: every fit made
    (folder / "discover.log").unlink(missing_ok=True)  # the log of this attempt only
    done = launch_otgb(args, folder / "discover.log", cwd=folder)
    report = newest(folder, "runs/*/version_*/report.json")
    for name in ("report.json", "report.md") if report else ():
        (folder / name).write_text((report.parent / name).read_text())
    found = json.loads(report.read_text()) if report and done.returncode == 0 else None
    return found, {"seconds": done.seconds, "returncode": done.returncode, "machine": machine()}


def run_once(
    folder: Path, write_measured: Callable[[Path], Path], config: str, overrides: list[str], seed: int,
    summarise: Callable[[dict | None], dict],
) -> dict:  # fmt: skip
    """One case of a benchmark, resumable: the ``summary.json`` in ``folder`` where it finished, else the measured file
    written by ``write_measured(folder)``, :func:`discover_file` on it and ``summarise(report)`` with the timing,
    written there (the file is removed: the script rewrites it from its seed, the report keeps what was found)."""
    if (folder / "summary.json").exists():
        print(f"{folder.name}: done")
        return json.loads((folder / "summary.json").read_text())
    folder.mkdir(parents=True, exist_ok=True)
    measured = write_measured(folder)
    report, timing = discover_file(folder, config, measured.name, overrides, seed)
    summary = summarise(report) | timing
    measured.unlink()
    (folder / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{folder.name}: exit {timing['returncode']} in {timing['seconds'] / 60:.1f} min: {summary.get('right')}")
    return summary


def case_parser(description: str, cases: dict, seeds: list[int]) -> argparse.ArgumentParser:
    """The arguments such a benchmark takes: its results folder, the cases and seeds to run, and ``--table``, a page to
    gather the finished runs into instead."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cases", nargs="+", choices=sorted(cases), default=list(cases))
    parser.add_argument("--seeds", nargs="+", type=int, default=seeds)
    parser.add_argument("--table", type=Path, help="only gather the finished runs into this Markdown page's markers")
    return parser
