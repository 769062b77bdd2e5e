"""Train with `otgb fit`, then test the best checkpoint; print the learning curve and test figures.

    python scripts/fit_and_report.py --config configs/pendulum.yaml --name bench [-- OVERRIDES...]

Everything after ``--`` goes to ``otgb fit`` unchanged (e.g. ``--data.simulation_budget 100000``).
Logs go to ``runs/<name>/version_N``; the curve (simulations, wall time, validation error) and
the test table (``metrics.md`` of the `otgb test` run, whose ``metrics.json`` holds the same) are
printed and written to ``report.md`` in the fit's run directory.
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import time
from pathlib import Path

from otgb.command import logger_override
from otgb.runs import newest


def read_rows(run: Path) -> list[dict[str, str]]:
    with open(run / "metrics.csv") as f:
        return list(csv.DictReader(f))


def curve(rows: list[dict[str, str]], metric: str) -> list[tuple[int, float, float, float]]:
    return [
        (int(r["step"]), float(r["val/simulations"]), float(r["val/wall_time_s"]), float(r[metric]))
        for r in rows
        if r.get(metric) and r.get("val/simulations")
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True)
    parser.add_argument("--name", required=True)
    parser.add_argument("--save-dir", default="runs")
    parser.add_argument("--metric", default="val/abs_err", help="validation metric for the curve")
    parser.add_argument("overrides", nargs=argparse.REMAINDER)
    args = parser.parse_args()
    overrides = [a for a in args.overrides if a != "--"]
    common = [
        "--config",
        args.config,
        logger_override(args.save_dir, args.name),
        "--trainer.enable_progress_bar=false",
        *overrides,
    ]

    start = time.perf_counter()
    subprocess.run(["otgb", "fit", *common], check=True)
    fit_seconds = time.perf_counter() - start
    run = newest(Path(args.save_dir) / args.name, "version_*")
    best = sorted((run / "checkpoints").glob("best-*.ckpt"))
    if not best:
        sys.exit(f"no best checkpoint in {run / 'checkpoints'}")
    subprocess.run(["otgb", "test", *common, f"--ckpt_path={best[-1]}"], check=True)
    test_run = newest(Path(args.save_dir) / args.name, "version_*")

    lines = [
        f"# {args.name}: `otgb fit --config {args.config} {' '.join(overrides)}`",
        "",
        f"fit wall time {fit_seconds:.0f} s (process, including start-up); best checkpoint {best[-1].name}",
        "",
        f"| step | simulations | wall time (s) | {args.metric} |",
        "|---|---|---|---|",
    ]
    lines += [f"| {s} | {n:.0f} | {t:.0f} | {m:.4f} |" for s, n, t, m in curve(read_rows(run), args.metric)]
    lines += ["", (test_run / "metrics.md").read_text()]
    report = "\n".join(lines) + "\n"
    (run / "report.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
