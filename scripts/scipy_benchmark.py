"""Benchmark of ``otgb discover``'s forms and recalibration on files from an independent solver (SciPy, not otgb).

    python scripts/scipy_benchmark.py --out results/scipy                                # every case, seed 0
    python scripts/scipy_benchmark.py --out results/scipy --cases rational --seeds 0 1 2
    python scripts/scipy_benchmark.py --out results/scipy --cases weaker_20 weaker_40 --folds 5
    python scripts/scipy_benchmark.py --out results/scipy --table docs/discovery.md      # gather only

Each case is a pendulum file of 1000 trajectories written by ``scripts/scipy_pendulum.py`` (theta and x0 not
recorded, the angle with white noise of sd 0.02), given to README's discover command. A saturating friction
must be named as one, its coefficient and speed within 20 %, the gap closed; a viscous friction, and viscous plus
Coulomb friction, must not be named as a form; a restoring force 20 % or 40 % weaker than f_p's must be a
recalibration of omega's prior, both bounds within 5 %, no term named. "right" is "alike" where another form was
named and the verdict says that the validation part cannot tell the law's form from it. ``--folds K`` runs the
cases with ``--discover.folds K`` (cross-fitted evidence), in folders of their own (``<case>-seed<s>-K<K>``).

Finished runs (a ``summary.json``, with the run's report.json and report.md beside it) are skipped, so an
interrupted benchmark resumes; ``--table`` writes the gathered runs between the markers of the page given.
"""

from __future__ import annotations

import json
from pathlib import Path

from discover_file import case_parser, run_once
from scipy_pendulum import write

from otgb.reports import write_between

DISCOVER = ["--data.hidden_effect=[]", "--data.measurement_noise=0.02", "--data.simulation_budget=32000"]
# name -> (law, c, v0, ratio, restoring force's scale, what must be named: a form's name, None for library terms
# only, or "omega" for a recalibration of omega's prior and no term)
CASES = {
    "rational": ("rational", 0.8, 2.0, 0.0, 1.0, "rational"),  # v0 about half the largest speed (3.9 rad/s)
    "tanh": ("tanh", 0.8, 1.0, 0.0, 1.0, "saturating"),
    "viscous": ("viscous", 0.8, 1.0, 0.0, 1.0, None),
    "viscous_coulomb": ("viscous_coulomb", 0.6, 1.0, 0.3, 1.0, None),
    "weaker_20": ("none", 0.0, 1.0, 0.0, 0.8, "omega"),  # omega ~ U(0.702, 2.809)
    "weaker_40": ("none", 0.0, 1.0, 0.0, 0.6, "omega"),  # omega ~ U(0.608, 2.432)
}
TRUTH = {  # the coefficient and parameters a named form should have, or the bounds of omega's recalibrated prior
    "rational": {"coefficient": -0.8, "v0": 2.0},
    "tanh": {"coefficient": -0.8, "v0": 1.0},
    "weaker_20": {"low": 0.785 * 0.8**0.5, "high": 3.14 * 0.8**0.5},
    "weaker_40": {"low": 0.785 * 0.6**0.5, "high": 3.14 * 0.6**0.5},
}


def run_case(case: str, seed: int, out: Path, folds: int = 1) -> dict:
    law, c, v0, ratio, restoring, _ = CASES[case]
    write_measured = lambda folder: write(folder / "measured.csv", law, c, v0, ratio, 1000, seed, 0.02, restoring)  # noqa: E731
    summary = lambda report: summarise(case, report) | {"folds": folds}  # noqa: E731
    folder = out / (f"{case}-seed{seed}" + (f"-K{folds}" if folds > 1 else ""))
    return run_once(folder, write_measured, "pendulum.yaml", [*DISCOVER, f"--discover.folds={folds}"], seed, summary)


def summarise(case: str, report: dict | None) -> dict:
    """What the run named (terms, a form's parameters with intervals), its outcome and C2ST, and whether it is right."""
    if report is None:
        return {"case": case, "terms": [], "outcome": "failed", "right": "no"}
    terms = [
        {"name": t["name"], "feature": t["feature"], "coefficient": t["coefficient"], "interval": t["interval"],
         "parameters": t.get("parameters") or []}
        for t in report["terms"]
    ]  # fmt: skip
    forms, alike = [t for t in terms if t["parameters"]], (report.get("forms") or {}).get("alike", [])
    wanted, closed = CASES[case][5], report["outcome"] == "gap closed"
    omega = next((r["prior"] for r in report.get("recalibrated") or [] if r["parameter"] == "omega"), None)
    if wanted == "omega":
        right = "yes" if closed and not terms and omega and within(omega, TRUTH[case], 0.05) else "no"
    elif wanted is None:
        right = "yes" if closed and not forms else "no"
    elif closed and len(forms) == 1 and forms[0]["feature"].startswith(f"{wanted}(") and within(forms[0], TRUTH[case]):
        right = "yes"
    else:  # the law's form said to be indistinguishable from the one named
        right = "alike" if closed and len(forms) == 1 and any(a.startswith(f"{wanted}(") for a in alike) else "no"
    gap = {k: v["c2st"] for k, v in report["gap"].items()}
    recalibrated = [{"parameter": r["parameter"], "prior": r["prior"], "bounds_intervals": r["bounds_intervals"]}
                    for r in report.get("recalibrated") or []]  # fmt: skip
    summary = {"case": case, "terms": terms, "recalibrated": recalibrated, "outcome": report["outcome"], "c2st": gap}
    return summary | {"right": right, "verdict": report["verdict"]}


def within(found: dict, truth: dict, tolerance: float = 0.2) -> bool:
    """Whether a named form's coefficient and parameters (or a recalibrated prior's bounds) lie within ``tolerance``
    of the truth."""
    values = {**found, **{p["name"]: p["value"] for p in found.get("parameters", [])}}
    return all(abs(values[k] - v) <= tolerance * abs(v) for k, v in truth.items())


def table(out: Path) -> str:
    header = "| case | seed | K | named | form's parameters (95 % interval) | outcome | C2ST f_p / augmented / Reference |"
    rows = [header + " right | min |", "|---|---|---|---|---|---|---|---|---|"]
    for path in sorted(out.glob("*-seed*/summary.json")):
        s = json.loads(path.read_text())
        named = ", ".join(f"{t['name']} {t['coefficient']:.3g}" for t in s["terms"])
        named = ", ".join([named] * bool(named) + [_prior(r) for r in s.get("recalibrated", [])]) or "nothing"
        parameters = "; ".join(
            f"{p['name']} = {p['value']:.3g}" + (f" [{p['interval'][0]:.3g}, {p['interval'][1]:.3g}]" if p["interval"] else "")
            for t in s["terms"] for p in t["parameters"]
        ) or "-"  # fmt: skip
        c2st = " / ".join(f"{s['c2st'][k]:.2f}" if k in s.get("c2st", {}) else "-" for k in ("f_p", "augmented", "reference"))
        seed = path.parent.name.rpartition("seed")[2].partition("-")[0]
        right, minutes, folds = s["right"], f"{s['seconds'] / 60:.1f}", s.get("folds", 1)
        rows.append(
            f"| {s['case']} | {seed} | {folds} | {named} | {parameters} | {s['outcome']} | {c2st} | {right} | {minutes} |"
        )
    return "\n".join(rows)


def _prior(record: dict) -> str:
    prior = record["prior"]
    said = ", ".join(f"{k} {v:.4g}" for k, v in prior.items() if k != "kind")
    bounds = record["bounds_intervals"]
    shown = f" (95 %: [{bounds[0][0]:.3g}, {bounds[0][1]:.3g}], [{bounds[1][0]:.3g}, {bounds[1][1]:.3g}])" if bounds else ""
    return f"{record['parameter']}'s prior {prior['kind']} {said}{shown}"


START, END = "<!-- table: scripts/scipy_benchmark.py --table -->", "<!-- end forms table -->"


def main() -> None:
    parser = case_parser(__doc__.split("\n\n")[0], CASES, [0])
    parser.add_argument("--folds", type=int, default=1, help="discover.folds of the runs (cross-fitted evidence)")
    args = parser.parse_args()
    if args.table:
        write_between(args.table, START, END, table(args.out))
        return
    for seed in args.seeds:
        for case in args.cases:
            run_case(case, seed, args.out, args.folds)


if __name__ == "__main__":
    main()
