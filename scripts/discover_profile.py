"""Where the time of a whole ``otgb discover`` run goes, stage by stage, on Table 1's measured files::

    python scripts/discover_profile.py --out results/profile --cases advdiff          # resumable
    python scripts/discover_profile.py --out results/profile --cases reactdiff --seeds 0 1 2
    python scripts/discover_profile.py --out results/profile --table docs/benchmarks.md   # gather only

A case is a task config: its measured set (f_p plus the config's hidden effect, seeded, as
``scripts/reproduce_table.py`` writes it for Table 1's discover row) given to ``otgb discover`` with the config's own
budgets and no fit cache, the grey-box trained inside the run. Each run's ``stages.json``
(:mod:`otgb.discovery.stages`: every stage's own wall seconds) is kept with its report beside a ``summary.json``
(the named terms, the outcome, the wall time and the machine); finished cases are skipped. ``--table`` writes, between
the page's markers, a stage's seconds per run with its share of the run, the stages longest first.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from discover_file import case_parser, run_once

from otgb.discovery.stages import OTHER
from otgb.reports import write_between
from otgb.runs import newest

ROOT = Path(__file__).parents[1]
CASES = {"advdiff": "advdiff.yaml", "reactdiff": "reactdiff.yaml", "pendulum": "pendulum.yaml"}
START, END = "<!-- table: scripts/discover_profile.py --table -->", "<!-- end profile table -->"


def run_case(case: str, seed: int, out: Path) -> dict:
    config = ROOT / "configs" / CASES[case]
    seeds = [f"--seed_everything={seed}", f"--data.seed={seed}"]

    def write_measured(folder: Path) -> Path:
        measured = folder / "measured.npz"
        measured.unlink(missing_ok=True)  # a stopped attempt's file: written again from its seed
        export = [sys.executable, str(ROOT / "scripts" / "export_measured.py"), "--config", str(config), "--out", str(measured)]
        subprocess.run([*export, *seeds], check=True, stdout=subprocess.DEVNULL)
        return measured

    def summarise(report: dict | None) -> dict:
        folder = out / f"{case}-seed{seed}"
        stages = newest(folder, "runs/*/version_*/stages.json")
        if stages is not None:
            (folder / "stages.json").write_text(stages.read_text())
        if report is None:
            return {"case": case, "terms": [], "outcome": "failed"}
        terms = [{"term": f"{t['feature']} on d{t['component']}/dt", "coefficient": t["coefficient"]} for t in report["terms"]]
        return {"case": case, "terms": terms, "outcome": report["outcome"]}

    return run_once(out / f"{case}-seed{seed}", write_measured, CASES[case], ["--data.hidden_effect=[]"], seed, summarise)


def table(out: Path) -> str:
    """Per stage, its seconds in each run and its median share; a run's total and named terms below."""
    runs = [p.parent for p in sorted(out.glob("*-seed*/stages.json"))]
    if not runs:
        return "(no finished runs)"
    records = {run.name: json.loads((run / "stages.json").read_text()) for run in runs}
    seconds = {name: {r["stage"]: r["seconds"] for r in rec["stages"]} for name, rec in records.items()}
    totals = {name: rec["total_seconds"] for name, rec in records.items()}
    stages = sorted({s for run in seconds.values() for s in run if s != OTHER}, key=lambda s: -max(_share(seconds, totals, s)))
    lines = ["| stage | " + " | ".join(records) + " |", "|---|" + "---|" * len(records)]
    for s in [*stages, OTHER]:
        cells = [f"{seconds[n].get(s, 0.0) / 60:.2f} min ({seconds[n].get(s, 0.0) / totals[n]:.0%})" for n in records]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    lines.append("| **whole run** | " + " | ".join(f"**{totals[n] / 60:.1f} min**" for n in records) + " |")
    summaries = [json.loads((run / "summary.json").read_text()) for run in runs]
    named = [", ".join(f"{t['term']} {t['coefficient']:.3g}" for t in s["terms"]) or s["outcome"] for s in summaries]
    lines.append("| named | " + " | ".join(named) + " |")
    machines = sorted({s["machine"] for s in summaries})
    return "\n".join(lines) + f"\n\nMachine: {'; '.join(machines)}."


def _share(seconds: dict, totals: dict, stage: str) -> list[float]:
    return [run.get(stage, 0.0) / totals[name] for name, run in seconds.items()]


def main() -> None:
    parser = case_parser(__doc__.split("\n\n")[0], CASES, [0])
    args = parser.parse_args()
    if args.table:
        write_between(args.table, START, END, table(args.out))
        return
    for seed in args.seeds:
        for case in args.cases:
            run_case(case, seed, args.out)


if __name__ == "__main__":
    main()
