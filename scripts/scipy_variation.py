"""Benchmark of ``otgb discover``'s varying families on files from independent solvers (SciPy, not otgb).

    python scripts/scipy_variation.py --out results/scipy_variation                      # every case, 3000 and 1000
    python scripts/scipy_variation.py --out results/scipy_variation --cases drag_varying --sizes 3000 --seeds 0 1
    python scripts/scipy_variation.py --out results/scipy_variation --cases drag_varying --sizes 3000 --folds 5
    python scripts/scipy_variation.py --out results/scipy_variation --table docs/discovery.md    # gather only

Each case's file (theta and x0 not recorded) holds a pendulum (``scripts/scipy_pendulum.py``, the angle with noise
of sd 0.02) or a rod (``scripts/scipy_advdiff.py``, the field with noise of sd 0.01) whose missing term's coefficient
each trajectory draws from a uniform prior (``*_varying``) or is one constant (``*_constant``), given to README's
discover command. A varying case is right where the term is named with a family that varies, its spread's 95 %
interval (as a standard deviation) holds the truth's, its centre lies within 10 % and the gap is closed; a constant
case, where no family that varies is claimed. ``--folds K`` runs them with ``--discover.folds K`` (cross-fitted
evidence), in folders of their own.

Finished runs (a ``summary.json`` with the run's report.json and report.md) are skipped, so an interrupted benchmark
resumes; ``--table`` writes the gathered runs between the markers of the page given.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import scipy_advdiff
import scipy_pendulum
from discover_file import case_parser, run_once

from otgb.reports import write_between

PENDULUM = ["--data.hidden_effect=[]", "--data.measurement_noise=0.02", "--data.simulation_budget=32000"]
ADVDIFF = ["--data.hidden_effect=[]", "--data.measurement_noise=0.01", "--data.simulation_budget=48000"]
# name -> (system, the pendulum's friction law, the term's feature, its coefficient's centre, the uniform's half-width)
CASES = {
    "viscous_varying": ("pendulum", "viscous", "velocity", -1.0, 0.5),  # U(-1.5, -0.5)
    "drag_varying": ("pendulum", "drag", "velocity*|velocity|", -0.5, 0.25),  # U(-0.75, -0.25)
    "decay_varying": ("advdiff", None, "T", -0.6, 0.3),  # U(-0.9, -0.3)
    "viscous_constant": ("pendulum", "viscous", "velocity", -1.0, 0.0),
    "drag_constant": ("pendulum", "drag", "velocity*|velocity|", -0.5, 0.0),
    "decay_constant": ("advdiff", None, "T", -0.6, 0.0),
}
SD_PER_HALF_WIDTH = {"uniform": 1 / math.sqrt(3), "normal": 1.0, "choice": 1.0}  # a family's width as an sd


def measured_file(case: str, folder: Path, n: int, seed: int) -> Path:
    system, law, _, centre, half_width = CASES[case]
    if system == "pendulum":
        return scipy_pendulum.write(folder / "measured.csv", law, -centre, 1.0, 0.0, n, seed, 0.02, spread=half_width)
    return scipy_advdiff.write(folder / "measured.npz", -centre, half_width, n, seed, 0.01)


def run_case(case: str, n: int, seed: int, out: Path, folds: int = 1) -> dict:
    system = CASES[case][0]
    overrides = [*(PENDULUM if system == "pendulum" else ADVDIFF), f"--discover.folds={folds}"]
    summary = lambda report: summarise(case, report) | {"n": n, "seed": seed, "folds": folds}  # noqa: E731
    write = lambda folder: measured_file(case, folder, n, seed)  # noqa: E731
    folder = out / (f"{case}-n{n}-seed{seed}" + (f"-K{folds}" if folds > 1 else ""))
    return run_once(folder, write, f"{system}.yaml", overrides, seed, summary)


def summarise(case: str, report: dict | None) -> dict:
    """The named terms with their families, centres and spreads (as standard deviations, 95 % intervals), the outcome,
    the C2STs, and whether the case is right."""
    if report is None:
        return {"case": case, "terms": [], "outcome": "failed", "right": "no"}
    _, _, feature, centre, half_width = CASES[case]
    terms = [_term(t) for t in report["terms"]]
    varying = [t for t in terms if t["family"]]  # a constant term has no distribution
    closed = report["outcome"] == "gap closed"
    if half_width == 0:
        right = "no" if varying else "yes"
    else:
        truth_sd = half_width * SD_PER_HALF_WIDTH["uniform"]
        term = next((t for t in varying if t["feature"] == feature), None)
        holds = term is not None and term["spread_sd"] is not None and term["spread_sd"][0] <= truth_sd <= term["spread_sd"][1]
        near = term is not None and abs(term["coefficient"] - centre) <= 0.1 * abs(centre)
        right = "yes" if holds and near and closed else "no"
    gap = {k: v["c2st"] for k, v in report["gap"].items()}
    return {"case": case, "terms": terms, "outcome": report["outcome"], "c2st": gap, "right": right, "verdict": report["verdict"]}


def _term(t: dict) -> dict:
    family = (t.get("distribution") or {}).get("kind")
    scale = SD_PER_HALF_WIDTH.get(family)
    spread = [scale * w for w in t["spread_interval"]] if scale and t.get("spread_interval") else None
    excluded = t.get("excluded_spread")
    return {
        "name": t["name"],
        "feature": t["feature"],
        "coefficient": t["coefficient"],
        "interval": t["interval"],
        "family": family,
        "distribution": t.get("distribution"),
        "spread_sd": spread,
        "excluded_spread": excluded,
    }


def table(out: Path) -> str:
    lines = [
        "| case | trajectories | K | seed | truth | named (family) | spread as sd, 95 % (truth) | outcome | C2ST f_p /"
        " augmented / Reference | right | min |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for path in sorted(out.glob("*/summary.json"), key=_order):
        s = json.loads(path.read_text())
        _, _, feature, centre, half_width = CASES[s["case"]]
        truth = (
            f"{feature}: U({centre - half_width:.3g}, {centre + half_width:.3g})" if half_width else f"{feature}: {centre:.3g}"
        )
        named = ", ".join(f"{t['feature']} {t['coefficient']:.3g} ({t['family'] or 'constant'})" for t in s["terms"]) or "nothing"
        spreads = "; ".join(f"[{t['spread_sd'][0]:.3g}, {t['spread_sd'][1]:.3g}]" for t in s["terms"] if t["spread_sd"]) or "-"
        spreads += f" ({half_width * SD_PER_HALF_WIDTH['uniform']:.3g})"
        c2st = " / ".join(f"{s['c2st'][k]:.2f}" if k in s.get("c2st", {}) else "-" for k in ("f_p", "augmented", "reference"))
        minutes = f"{s['seconds'] / 60:.1f}"
        lines.append(
            f"| {s['case']} | {s['n']} | {s.get('folds', 1)} | {s['seed']} | {cell(truth)} | {cell(named)} | {spreads} "
            f"| {s['outcome']} | {c2st} | {s['right']} | {minutes} |"
        )
    return "\n".join(lines + ["", _tally(out)])


def cell(text: str) -> str:
    """``text`` for a Markdown table's cell: a feature's own bars (``velocity*|velocity|``) escaped."""
    return text.replace("|", "\\|")


def _order(path: Path) -> tuple:
    s = json.loads(path.read_text())
    return (s["case"], s["n"], s.get("folds", 1), s["seed"])


def _tally(out: Path) -> str:
    """Per case, size and number of folds: right in how many of the files run."""
    counts: dict[tuple[str, int, int], list[int]] = {}
    for path in out.glob("*/summary.json"):
        s = json.loads(path.read_text())
        counts.setdefault((s["case"], s["n"], s.get("folds", 1)), []).append(s["right"] == "yes")
    said = [f"{case} at {n}, K = {k}: right in {sum(v)} of {len(v)}" for (case, n, k), v in sorted(counts.items())]
    return "Right, per case, number of trajectories and folds K: " + "; ".join(said) + "."


START, END = "<!-- table: scripts/scipy_variation.py --table -->", "<!-- end variation table -->"


def main() -> None:
    parser = case_parser(__doc__.split("\n\n")[0], CASES, [0, 1, 2, 3, 4])
    parser.add_argument("--sizes", nargs="+", type=int, default=[3000, 1000])
    parser.add_argument("--folds", type=int, default=1, help="discover.folds of the runs (cross-fitted evidence)")
    args = parser.parse_args()
    if args.table:
        write_between(args.table, START, END, table(args.out))
        return
    for n in args.sizes:
        for seed in args.seeds:
            for case in args.cases:
                run_case(case, n, seed, args.out, args.folds)


if __name__ == "__main__":
    main()
