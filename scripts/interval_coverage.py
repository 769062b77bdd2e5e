"""How often ``otgb discover``'s 95 % intervals cover the truth: the interval step alone, on fresh measured files.

    python scripts/interval_coverage.py --case friction --files 20      # writes results/intervals/friction/
    python scripts/interval_coverage.py --table                         # coverage per case, from the result files

Per file: measurements drawn anew from f_p plus one known term (the seed differs per file),
the term's coefficient fitted to the first 70 % of them by distribution matching
(:func:`otgb.discovery.refine.fit`, the workflow's fit, from half the truth as f_phi's
regression would roughly give it) and its interval from the fit's sandwich
(:mod:`otgb.discovery.intervals`, the workflow's settings). Each file's result is one JSON
file, written as it finishes: an interrupted study resumes where it stopped. ``--table``
writes the coverage table into docs/discovery.md between its markers.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from result_tables import header, results_in, row

from otgb.data import generate_measured
from otgb.discovery.families import centre, spread
from otgb.discovery.intervals import sandwich_intervals
from otgb.discovery.library import Candidate
from otgb.discovery.refine import fit
from otgb.physics import AdvectionDiffusion, Choice, Constant, LibraryTerm, Pendulum, Uniform
from otgb.reports import write_between

ROOT = Path(__file__).parents[1]
OUT = ROOT / "results" / "intervals"
DOC = ROOT / "docs" / "discovery.md"
MARK = "<!-- coverage: scripts/interval_coverage.py -->"

# name -> (f_p, feature, component, prior of the truth, family fitted, measured trajectories, fit batch)
CASES = {
    "friction": (Pendulum, "velocity", "velocity", Constant(-1.2), "constant", 1000, 1024),
    "drag": (Pendulum, "velocity*|velocity|", "velocity", Constant(-0.5), "constant", 1000, 1024),
    "advection": (AdvectionDiffusion, "d_s(T)", "T", Constant(-0.1), "constant", 1000, 1024),
    "stochastic_friction": (Pendulum, "velocity", "velocity", Uniform(-1.5, -0.6), "uniform", 1000, 1024),
    "two_point_friction": (Pendulum, "velocity", "velocity", Choice([-1.5, -0.6]), "two_point", 1000, 1024),
}


def truth(prior) -> dict[str, float]:
    """The true centre (and half-width) of the hidden coefficient."""
    if prior.is_constant:
        return {"centre": prior.value}
    return {"centre": centre(prior), "width": spread(prior)}


def one_file(case: str, index: int, steps: int) -> dict:
    physics_class, feature, component, prior, family, n, batch = CASES[case]
    dgp = physics_class().with_hidden_effect([LibraryTerm(feature, component, prior)])
    measured = generate_measured(dgp, n, 5000 + index)["y"]
    train, heldout = measured[: int(0.7 * n)], measured[int(0.7 * n) :]
    true = truth(prior)
    start, scale = 0.5 * true["centre"], abs(true["centre"])
    candidate = Candidate(feature, component)
    began = time.monotonic()
    if family == "constant":
        estimate = fit(physics_class(), [candidate], [start], family, train, heldout, steps, batch, index, False, [scale])
    else:  # as the workflow does: the richer family starts at the constant fit's value
        constant = fit(physics_class(), [candidate], [start], "constant", train, heldout, steps, batch, index, False, [scale])
        start = constant.priors[0].value
        estimate = fit(physics_class(), [candidate], [start], family, train, heldout, steps, batch, index, False)
    fitted_seconds = time.monotonic() - began
    intervals = sandwich_intervals(physics_class(), estimate, train, batch, index)
    row = {"case": case, "file": index, "truth": true, "fit_seconds": fitted_seconds}
    row["interval_seconds"] = time.monotonic() - began - fitted_seconds
    prior_fit = estimate.priors[0]
    row["estimate"] = {"centre": centre(prior_fit)}
    if intervals is None:
        row["interval"] = None
        return row
    row["interval"] = {"centre": intervals.centre[0]}
    row["covers"] = {"centre": intervals.centre[0][0] <= true["centre"] <= intervals.centre[0][1]}
    if intervals.width is not None:
        row["estimate"]["width"] = spread(prior_fit)
        row["interval"]["width"] = intervals.width[0]
        row["covers"]["width"] = intervals.width[0][0] <= true["width"] <= intervals.width[0][1]
    return row


def study(case: str, files: int, steps: int) -> None:
    folder = OUT / case
    folder.mkdir(parents=True, exist_ok=True)
    for index in range(files):
        path = folder / f"file{index:02d}.json"
        if path.exists():
            continue
        row = one_file(case, index, steps)
        path.write_text(json.dumps(row, indent=1))
        print(f"{case} file {index}: {row['estimate']} {row['interval']} covers {row.get('covers')}", flush=True)


def coverage_table() -> str:
    columns = ["case", "files", "truth", "parameter", "covered", "coverage [95 %]", "mean interval width"]
    lines = header([*columns, "interval time per file"])
    for case in CASES:
        rows = list(results_in(OUT / case, "file*.json").values())
        if not rows:
            continue
        for part in rows[0]["truth"]:
            covered = sum(bool(r.get("covers", {}).get(part)) for r in rows)
            widths = [r["interval"][part][1] - r["interval"][part][0] for r in rows if r["interval"]]
            seconds = sum(r["interval_seconds"] for r in rows) / len(rows)
            low, high = wilson(covered, len(rows))
            true, coverage = f"{rows[0]['truth'][part]:.4g}", f"{covered / len(rows):.2f} [{low:.2f}, {high:.2f}]"
            width = f"{sum(widths) / max(len(widths), 1):.4g}"
            lines.append(row([case, len(rows), true, part, covered, coverage, width, f"{seconds:.2g} s"]))
    return "\n".join(lines)


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson's 95 % interval of a proportion k / n."""
    p, denominator = k / n, 1 + z * z / n
    middle = (p + z * z / (2 * n)) / denominator
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denominator
    return max(0.0, middle - half), min(1.0, middle + half)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", choices=list(CASES))
    parser.add_argument("--files", type=int, default=20)
    parser.add_argument("--steps", type=int, default=50, help="as otgb discover's discover.fit_steps")
    parser.add_argument("--table", action="store_true", help="write the coverage table into --doc")
    parser.add_argument("--doc", type=Path, default=DOC, help="the page with the table's markers")
    args = parser.parse_args()
    if args.case:
        study(args.case, args.files, args.steps)
    if args.table:
        write_between(args.doc, MARK, MARK, coverage_table())


if __name__ == "__main__":
    main()
