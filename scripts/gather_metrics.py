"""Gather the ``metrics.json`` of several `otgb test` runs into one Table-1-style Markdown table.

    python scripts/gather_metrics.py runs/*/version_*/metrics.json [--metrics nrmse abs_err] [--out table.md]

Runs are grouped by their run name (the logger name) with a trailing seed tag such as
``_seed3`` or ``_s3`` removed (``--seed-suffix`` changes the pattern), so the runs of one
task over several seeds form one row. Each cell is the mean ± std across the group's runs of
the per-run figure (the std is left out for a single run); f_p alone and the Reference
are given next to the model.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from result_tables import header, row

from otgb.reports import HEADERS, LABELS, SOURCES, mean_spread


def load(paths: list[Path]) -> list[dict]:
    runs = []
    for path in paths:
        try:
            content = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as error:
            sys.exit(f"{path}: cannot read a metrics.json ({error})")
        if "run" not in content or "model" not in content:
            sys.exit(f"{path}: not an otgb metrics.json (no 'run'/'model' entries)")
        runs.append(content)
    return runs


def group_runs(runs: list[dict], seed_suffix: str) -> dict[str, list[dict]]:
    groups: dict[str, list[dict]] = {}
    for run in runs:
        name = re.sub(seed_suffix, "", str(run["run"].get("name")))
        groups.setdefault(name, []).append(run)
    return groups


def metric_cell(runs: list[dict], source: str, metric: str) -> str:
    return mean_spread([r[source][metric]["mean"] for r in runs if metric in r.get(source, {})])


def table(groups: dict[str, list[dict]], metrics: list[str]) -> str:
    columns = [(m, s) for m in metrics for s in SOURCES]
    lines = header(["task", "runs", *(f"{LABELS[m]} ({HEADERS[s]})" for m, s in columns)])
    lines += [row([name, len(runs), *(metric_cell(runs, s, m) for m, s in columns)]) for name, runs in groups.items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="metrics.json files written by `otgb test`")
    parser.add_argument("--metrics", nargs="+", default=None, help=f"metrics to show (default: all present); of {list(LABELS)}")
    parser.add_argument("--seed-suffix", default=r"_s(eed)?\d+$", help="regex removed from run names to group seeds")
    parser.add_argument("--out", type=Path, help="also write the table to this file")
    args = parser.parse_args(argv)
    runs = load(args.files)
    present = [m for m in LABELS if any(m in r["model"] for r in runs)]
    metrics = args.metrics or present
    unknown = [m for m in metrics if m not in LABELS]
    if unknown:
        sys.exit(f"unknown metrics {unknown}; expected some of {list(LABELS)}")
    text = table(group_runs(runs, args.seed_suffix), metrics)
    if args.out:
        args.out.write_text(text)
    print(text, end="")


if __name__ == "__main__":
    main()
