"""Benchmark of cross-fitted evidence (``discover.folds``) against one validation part, on files from SciPy.

    python scripts/crossfit_benchmark.py --out results/crossfit                          # every case, K = 1 and 5
    python scripts/crossfit_benchmark.py --out results/crossfit --cases viscous_coulomb --seeds 0 1 --folds 5
    python scripts/crossfit_benchmark.py --out results/crossfit --table docs/discovery.md      # gather only

Each file (``scripts/scipy_pendulum.py``: 1000 pendulums, the angle with noise of sd 0.02, theta and x0 not recorded)
is given to README's discover command twice, with ``--discover.folds 1`` and ``5``:

- ``viscous_coulomb``: a viscous friction -0.6 v and a dry friction -0.3 sign(v) together (each at least a quarter of
  the RMS of the missing acceleration along the trajectories: :func:`shares` measures it); right where both are named,
  each within 15 %;
- ``viscous``: a viscous friction alone, its coefficient drawn per file from U(-1.0, -0.3); right where it alone is
  named, within 15 % (a second term added is a false discovery).

Finished runs (a ``summary.json``) are skipped, so an interrupted benchmark resumes; ``--table`` writes the gathered
runs between the markers of the page given.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import scipy_pendulum
from discover_file import case_parser, run_once
from scipy.integrate import solve_ivp
from scipy_variation import cell

from otgb.reports import write_between

OVERRIDES = ["--data.hidden_effect=[]", "--data.measurement_noise=0.02", "--data.simulation_budget=32000"]
TRAJECTORIES = 1000
FOLDS = (1, 5)
CASES = {"viscous_coulomb": ("velocity", "sign(velocity)"), "viscous": ("velocity",)}
COULOMB = 0.3
WITHIN = 0.15


def truth(case: str, seed: int) -> dict[str, float]:
    """The file's coefficients by feature."""
    if case == "viscous_coulomb":
        return {"velocity": -0.6, "sign(velocity)": -COULOMB}
    return {"velocity": -float(np.random.default_rng(1000 + seed).uniform(0.3, 1.0))}


def shares(c: float, dry: float, n: int = 200, seed: int = 0) -> dict[str, float]:
    """Each friction term's RMS over pendulums drawn as the files' are, as a share of their sum's RMS."""
    rng, t = np.random.default_rng(seed), np.arange(50) * 0.1
    viscous, coulomb, force = [], [], scipy_pendulum.LAWS["viscous_coulomb"]

    def field(_, y, omega):
        return [y[1], -(omega**2) * np.sin(y[0]) + force(y[1], c, 1.0, dry)]

    for _ in range(n):
        angle, omega = rng.uniform(-1.57, 1.57), rng.uniform(0.785, 3.14)
        v = solve_ivp(field, (0, t[-1]), [angle, 0.0], t_eval=t, args=(omega,), **scipy_pendulum.SOLVER).y[1]
        viscous.append(-c * v)
        coulomb.append(-dry * np.tanh(v / 1e-3))
    a, b = np.concatenate(viscous), np.concatenate(coulomb)
    total = np.sqrt(np.mean((a + b) ** 2))
    return {"velocity": float(np.sqrt(np.mean(a**2)) / total), "sign(velocity)": float(np.sqrt(np.mean(b**2)) / total)}


def measured_file(case: str, folder: Path, seed: int) -> Path:
    coefficients = truth(case, seed)
    law, dry = ("viscous_coulomb", COULOMB) if case == "viscous_coulomb" else ("viscous", 0.0)
    return scipy_pendulum.write(folder / "measured.csv", law, -coefficients["velocity"], 1.0, dry, TRAJECTORIES, seed, 0.02)


def run_case(case: str, seed: int, folds: int, out: Path) -> dict:
    overrides = [*OVERRIDES, f"--discover.folds={folds}"]
    summary = lambda report: summarise(case, seed, report) | {"seed": seed, "folds": folds}  # noqa: E731
    write = lambda folder: measured_file(case, folder, seed)  # noqa: E731
    return run_once(out / f"{case}-seed{seed}-K{folds}", write, "pendulum.yaml", overrides, seed, summary)


def summarise(case: str, seed: int, report: dict | None) -> dict:
    """The named terms and coefficients, whether the case is right and whether a term beyond the truth's was added."""
    coefficients = truth(case, seed)
    if report is None:
        return {"case": case, "truth": coefficients, "terms": {}, "outcome": "failed", "right": "no", "extra": None}
    terms = {t["feature"]: t["coefficient"] for t in report["terms"]}
    near = all(f in terms and abs(terms[f] - v) <= WITHIN * abs(v) for f, v in coefficients.items())
    extra = sorted(set(terms) - set(coefficients))
    right = "yes" if near and not extra and report["outcome"] == "gap closed" else "no"
    return {"case": case, "truth": coefficients, "terms": terms, "outcome": report["outcome"], "right": right, "extra": extra}


def table(out: Path) -> str:
    lines = [
        "| case | seed | K | truth | named | outcome | right | extra term | min |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    summaries = sorted((json.loads(p.read_text()) for p in out.glob("*/summary.json")), key=_order)
    for s in summaries:
        said = lambda terms: ", ".join(f"{f} {v:.3g}" for f, v in terms.items()) or "nothing"  # noqa: E731
        extra = ", ".join(s["extra"]) if s["extra"] else ("-" if s["extra"] is not None else "failed")
        lines.append(
            f"| {s['case']} | {s['seed']} | {s['folds']} | {cell(said(s['truth']))} | {cell(said(s['terms']))} | {s['outcome']} "
            f"| {s['right']} | {extra} | {s['seconds'] / 60:.1f} |"
        )
    share = shares(0.6, COULOMB)
    said = f"viscous {share['velocity']:.2f}, dry {share['sign(velocity)']:.2f}"
    note = f"In viscous_coulomb, each term's RMS as a share of the missing acceleration's (200 pendulums): {said}."
    return "\n".join(lines + ["", _tally(summaries), "", note])


def _order(s: dict) -> tuple:
    return (s["case"], s["seed"], s["folds"])


def _tally(summaries: list[dict]) -> str:
    """Per case and K: right in how many files, a second term added in how many, the median minutes."""
    said = []
    for case in CASES:
        for folds in FOLDS:
            runs = [s for s in summaries if s["case"] == case and s["folds"] == folds]
            if runs:
                right, extra = sum(s["right"] == "yes" for s in runs), sum(bool(s["extra"]) for s in runs)
                minutes = float(np.median([s["seconds"] for s in runs])) / 60
                counts = f"right in {right} of {len(runs)}, a term added in {extra}"
                said.append(f"{case}, K = {folds}: {counts}, median {minutes:.1f} min")
    return "Per case and K: " + "; ".join(said) + ". " + _ratios(summaries)


def _ratios(summaries: list[dict]) -> str:
    """Per case, K = 5's wall time over K = 1's on the same file: the median and the range over the files run with both."""
    said = []
    for case in CASES:
        seconds = {(s["seed"], s["folds"]): s["seconds"] for s in summaries if s["case"] == case}
        ratios = [seconds[seed, 5] / seconds[seed, 1] for seed, folds in seconds if folds == 5 and (seed, 1) in seconds]
        if ratios:
            low, median, high = min(ratios), float(np.median(ratios)), max(ratios)
            said.append(f"{case}: {median:.2f} (from {low:.2f} to {high:.2f}, {len(ratios)} files)")
    return "Wall time with K = 5 over K = 1, file by file: " + "; ".join(said) + "."


START, END = "<!-- table: scripts/crossfit_benchmark.py --table -->", "<!-- end crossfit table -->"


def main() -> None:
    parser = case_parser(__doc__.split("\n\n")[0], CASES, list(range(10)))
    parser.add_argument("--folds", nargs="+", type=int, choices=FOLDS, default=list(FOLDS), help="the K to run")
    args = parser.parse_args()
    if args.table:
        write_between(args.table, START, END, table(args.out))
        return
    for seed in args.seeds:
        for case in args.cases:
            if case == "viscous_coulomb" and seed >= 5:
                continue  # five files of the two frictions, ten of the viscous alone
            for folds in args.folds:
                run_case(case, seed, folds, args.out)


if __name__ == "__main__":
    main()
