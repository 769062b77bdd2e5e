"""Train with `otgb fit`, then test the best checkpoint; print the learning curve and test figures.

    python scripts/fit_and_report.py --config configs/pendulum.yaml --name bench [-- OVERRIDES...]

Everything after ``--`` goes to both commands unchanged (e.g. ``--data.simulation_budget 100000``).
Logs go to ``runs/<name>/fit/version_N`` and ``runs/<name>/test/version_N``
(:func:`otgb.runs.fit_and_test`: run again, it resumes an interrupted fit). The curve (simulations,
wall time, validation error) and the test table (``metrics.md`` of the `otgb test` run, whose
``metrics.json`` holds the same) are printed and written to ``runs/<name>/report.md``.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from otgb.runs import fit_and_test, newest


def curve(metrics_csv: Path, metric: str) -> list[tuple[int, float, float, float]]:
    with open(metrics_csv) as f:
        rows = list(csv.DictReader(f))
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
    folder = Path(args.save_dir) / args.name
    fitted = fit_and_test(folder, ["--config", args.config, *overrides])
    best = newest(folder / "fit", "version_*/checkpoints/best-*.ckpt")
    lines = [
        f"# {args.name}: `otgb fit --config {args.config} {' '.join(overrides)}`",
        "",
        f"fit wall time {fitted['fit_s']:.0f} s (process, including start-up); best checkpoint {best.name}",
        "",
        f"| step | simulations | wall time (s) | {args.metric} |",
        "|---|---|---|---|",
    ]
    lines += [f"| {s} | {n:.0f} | {t:.0f} | {m:.4f} |" for s, n, t, m in curve(best.parents[1] / "metrics.csv", args.metric)]
    lines += ["", newest(folder / "test", "version_*/metrics.md").read_text()]
    report = "\n".join(lines) + "\n"
    (folder / "report.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
