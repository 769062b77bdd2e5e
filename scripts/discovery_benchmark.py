"""Benchmark of ``otgb discover`` on measurements in which a known effect is hidden.

    python scripts/discovery_benchmark.py --out bench/discovery                       # every case, seed 0
    python scripts/discovery_benchmark.py --out bench/discovery --cases pendulum_friction --seeds 0 1 2 3 4
    python scripts/discovery_benchmark.py --out bench/discovery --table docs/discovery-table.md   # gather only

For each case and seed it writes the DGP's draws to ``<out>/<case>-seed<N>/measured.npz`` (the
only thing ``otgb discover`` is given: the hidden term is named nowhere in its arguments),
runs ``otgb discover`` on it with the case's config and budget, and records the wall time.
Finished runs (a ``report.json``) are skipped, so an interrupted benchmark resumes where it
stopped; a run interrupted during training starts again. ``--table`` gathers every finished
run into a Markdown table: the terms named against the truth, and C2ST of f_p, the grey-box,
the augmented physics and the Reference on held-out measurements.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from result_tables import read_json, row

from otgb.data import generate_measured
from otgb.discovery.prior_text import distribution_text
from otgb.physics import AdvectionDiffusion, Constant, LibraryTerm, Pendulum, ReactionDiffusion, Uniform
from otgb.reports import write_between
from otgb.runs import launch_otgb, machine, newest

ROOT = Path(__file__).parents[1]
PENDULUM = ["--data.simulation_budget=32000", "--trainer.val_check_interval=250"]
ADVDIFF = ["--data.simulation_budget=48000", "--trainer.val_check_interval=250"]


def term(feature: str, component: str, prior) -> LibraryTerm:
    return LibraryTerm(feature, component, prior)


# name -> (config, f_p, hidden terms, measured trajectories, DGP solver step, overrides)
CASES = {
    "pendulum_friction": ("pendulum.yaml", Pendulum, [term("velocity", "velocity", Constant(-1.2))], 1000, None, PENDULUM),
    "pendulum_drag": ("pendulum.yaml", Pendulum, [term("velocity*|velocity|", "velocity", Constant(-0.5))], 1000, None, PENDULUM),
    "pendulum_stochastic_friction": (
        "pendulum.yaml",
        Pendulum,
        [term("velocity", "velocity", Uniform(-1.5, -0.6))],
        1000,
        None,
        PENDULUM,
    ),  # fmt: skip
    "pendulum_stochastic_drag": (
        "pendulum.yaml",
        Pendulum,
        [term("velocity*|velocity|", "velocity", Uniform(-0.8, -0.2))],
        1000,
        None,
        PENDULUM,
    ),  # fmt: skip
    "pendulum_friction_drag": (
        "pendulum.yaml",
        Pendulum,
        [term("velocity", "velocity", Constant(-0.8)), term("velocity*|velocity|", "velocity", Constant(-0.4))],
        1000,
        None,
        PENDULUM,
    ),  # fmt: skip
    "pendulum_none": ("pendulum.yaml", Pendulum, [term("velocity", "velocity", Constant(0.0))], 1000, None, PENDULUM),
    "advdiff_advection": ("advdiff.yaml", AdvectionDiffusion, [term("d_s(T)", "T", Constant(-0.1))], 1000, None, ADVDIFF),
    "advdiff_decay": ("advdiff.yaml", AdvectionDiffusion, [term("T", "T", Constant(-0.5))], 1000, None, ADVDIFF),
    "advdiff_stochastic_decay": (
        "advdiff.yaml",
        AdvectionDiffusion,
        [term("T", "T", Uniform(-0.8, -0.2))],
        1000,
        None,
        ADVDIFF,
    ),  # fmt: skip
    "advdiff_heater": (
        "advdiff.yaml",
        AdvectionDiffusion,
        [term("s", "T", Constant(1.89)), term("s^2", "T", Constant(-0.9))],  # a heater 0.9 s (2.1 - s) along the rod
        1000,
        None,
        [*ADVDIFF, "--discover.position_degree=2"],
    ),  # fmt: skip
    "reactdiff_reaction": (
        "reactdiff.yaml",
        lambda: ReactionDiffusion(u_reaction=False),
        [
            term("u", "u", Constant(1.0)),
            term("u^3", "u", Constant(-1.0)),
            term("v", "u", Constant(-1.0)),
            term("1", "u", Constant(-5e-3)),
        ],
        500,
        1e-3,
        ["--discover.fit_batch=256", "--discover.n_trajectories=64"],  # a 2 x 32 x 32 field: fewer simulations per fit
    ),
}


def export(case: str, seed: int, noise: float, path: Path) -> None:
    """The DGP's draws (f_p plus the hidden terms), with Gaussian noise of ``noise`` times the data's std."""
    _, physics, terms, n, step, _ = CASES[case]
    y = generate_measured(physics().with_hidden_effect(terms, step_size=step), n, 1000 + seed)["y"]
    if noise > 0:
        g = torch.Generator().manual_seed(2000 + seed)
        y = y + noise * y.std() * torch.randn(y.shape, generator=g)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, y=y.numpy())


def run_case(case: str, seed: int, noise: float, out: Path, refit: bool = False) -> None:
    folder = out / f"{case}{'-noise' if noise else ''}-seed{seed}"
    if latest_report(folder) is None:
        discover(case, seed, noise, folder)
    else:
        print(f"{folder.name}: done")
    report = latest_report(folder)
    if report is not None and report["found"]:
        if not (folder / "extrapolation.json").exists():
            (folder / "extrapolation.json").write_text(json.dumps(extrapolation(case, report)))
        if latest_report(folder / "round2") is None:
            round_two(folder)
        if refit and not (folder / "correction_after.json").exists():
            correction_after(folder, CASES[case][-1])


def discover(case: str, seed: int, noise: float, folder: Path) -> None:
    """``otgb discover`` on the case's measured file (written first), timed."""
    measured = folder / "measured.npz"
    if not measured.exists():
        export(case, seed, noise, measured)
    config, *_, overrides = CASES[case]
    args = ["discover", "--config", str(ROOT / "configs" / config), "--data.hidden_effect=[]", f"--data.measured_path={measured}"]
    args += [
        f"--seed_everything={seed}",
        f"--data.seed={seed}",
        f"--discover.seed={seed}",
        "--trainer.enable_progress_bar=false",
        "--discover.fit_cache=null",  # timed: every fit made, also when a stopped benchmark runs the case again
        *overrides,
    ]
    (folder / "discover.log").unlink(missing_ok=True)  # the log of this attempt only
    done = launch_otgb(args, folder / "discover.log", cwd=folder)
    timing = {"seconds": done.seconds, "returncode": done.returncode, "machine": machine()}
    (folder / "wall_time.json").write_text(json.dumps(timing))
    print(f"{folder.name}: exit {done.returncode} in {done.seconds / 60:.1f} min")


def latest_report(folder: Path) -> dict | None:
    report = newest(folder, "runs/*/version_*/report.json")
    return json.loads(report.read_text()) if report else None


def round_two(folder: Path) -> None:
    """``otgb discover`` again, on the augmented.yaml the first round wrote: a correct model must show nothing."""
    augmented = sorted(folder.glob("runs/*/version_*/augmented.yaml"))[-1]
    second = folder / "round2"
    second.mkdir(exist_ok=True)
    print(f"{folder.name}: second round on {augmented}")
    (second / "discover.log").unlink(missing_ok=True)
    launch_otgb(["discover", "--config", str(augmented), "--trainer.enable_progress_bar=false"], second / "discover.log", second)


def correction_after(folder: Path, overrides: list[str]) -> None:
    """Train a grey-box on top of the augmented physics (``otgb fit --config augmented.yaml``): how large
    a correction does it still learn? Compared with the first round's grey-box (components.json)."""
    augmented = sorted(folder.glob("runs/*/version_*/augmented.yaml"))[-1]
    refit = folder / "refit"
    refit.mkdir(exist_ok=True)
    (refit / "fit.log").unlink(missing_ok=True)
    launch_otgb(["fit", "--config", str(augmented), "--trainer.enable_progress_bar=false", *overrides], refit / "fit.log", refit)
    shares = {}
    for name, root in (("f_p", folder), ("augmented", refit)):
        found = sorted(root.glob("runs/*/version_*/components.json"))
        if found:
            shares[name] = json.loads(found[-1].read_text())["summary"]["correction_share"]
    (folder / "correction_after.json").write_text(json.dumps(shares))


@torch.no_grad()
def extrapolation(case: str, report: dict, n: int = 200) -> dict:
    """Mean |y - y_DGP| of f_p and of the augmented physics on the DGP's inputs, over the training horizon and twice it.

    Deterministic cases only (a coefficient drawn per trajectory has no pointwise truth): the
    augmented physics takes its coefficients at the centre of their fitted prior.
    """
    _, physics, terms, _, step, _ = CASES[case]
    if any(not t.priors["coefficient"].is_constant for t in terms):
        return {}
    base = physics()
    long = physics()
    long.n_obs = 2 * base.n_obs
    dgp = long.with_hidden_effect(terms, step_size=step)
    named = [LibraryTerm(t["feature"], t["component"], Constant(t["coefficient"])) for t in report["terms"]]
    augmented = long.with_hidden_effect(named)
    g = torch.Generator().manual_seed(3000)
    x0, theta = long.sample_initial_state(n, g), long.sample_theta(n, g)
    truth = dgp.simulate(x0, theta, dgp.sample_effect_params(n, g))
    out = {}
    for name, model in (("f_p", long), ("augmented", augmented)):
        effect = model.sample_effect_params(n, g) if model.effect_dim else None
        error = (model.simulate(x0, theta, effect) - truth).abs()
        out[name] = {"train_horizon": float(error[:, : base.n_obs].mean()), "twice_horizon": float(error[:, base.n_obs :].mean())}
    return out


def truth_text(case: str) -> str:
    terms = CASES[case.split("-")[0]][2]
    return ", ".join(f"{t.feature} on d{t.component}/dt: {_prior_text(t.priors['coefficient'])}" for t in terms)


def _prior_text(prior) -> str:
    if isinstance(prior, Uniform):
        return f"U({prior.low:.3g}, {prior.high:.3g})"
    return f"{prior.value:.3g}" if hasattr(prior, "value") else repr(prior)


HEADER = (
    "| case | seed | named: coefficient [95 %]; or alike: an alternative the validation part cannot tell from it "
    "(SE > 0: the named fits better); not weighed against: a term it moves with that its run did not compare it with "
    "| truth | outcome | f_p C2ST | grey-box C2ST | augmented C2ST "
    "| Reference C2ST | round 2 on augmented.yaml | wall time |\n|---|---|---|---|---|---|---|---|---|---|---|"
)


def outcome_text(report: dict) -> str:
    """The verdict's outcome and the p-value of the test that decides it (nearer to the test part than f_p alone)."""
    said = report.get("outcome") or report["verdict"].split(":")[0]  # older reports have no outcome
    if "closer" not in report:
        return f"{said} (run before the nearer-than-f_p test)" if report["found"] else said
    closer = report["closer"]
    return f"{said} (nearer than f_p: p = {closer['pvalue']:.2g})" if closer else said


def table(out: Path) -> str:
    rows, extrapolated, corrections = [HEADER], [], []
    for folder in sorted(out.iterdir()):
        report = latest_report(folder)
        if report is None:
            continue
        case, seed = folder.name.rsplit("-seed", 1)
        named = "; ".join(_named(t, report) for t in report["terms"]) or "nothing"
        gap = report["gap"]
        reference = f"{gap['reference']['c2st']:.3f} ± {gap['reference']['c2st_std']:.3f}"
        second = latest_report(folder / "round2")
        round2 = "-" if second is None else "nothing found"
        if second is not None and second["found"]:
            round2 = "found " + "; ".join(_named(t, second) for t in second["terms"])
        timing = read_json(folder / "wall_time.json")
        wall = f"{timing['seconds'] / 60:.1f} min" if timing else "-"
        c2sts = [f"{gap[k]['c2st']:.3f}" if k in gap else "-" for k in ("f_p", "greybox", "augmented")]
        rows.append(row([case, seed, named, truth_text(case), outcome_text(report), *c2sts, reference, round2, wall]))
        if (folder / "correction_after.json").exists():
            shares = read_json(folder / "correction_after.json")
            corrections.append(row([case, *(f"{shares.get(m, float('nan')):.3g}" for m in ("f_p", "augmented"))]))
        if errors := read_json(folder / "extrapolation.json"):
            values = [f"{errors[m][h]:.4g}" for m in ("f_p", "augmented") for h in ("train_horizon", "twice_horizon")]
            extrapolated.append(row([case, seed, *values]))
    text = "\n".join(rows) + "\n"
    if extrapolated:
        text += "\nMean |y - y_DGP| on 200 DGP inputs, over the training horizon and over the second, unseen one:\n\n"
        text += "| case | seed | f_p, horizon | f_p, 2nd horizon | augmented, horizon | augmented, 2nd horizon |\n"
        text += "|---|---|---|---|---|---|\n" + "\n".join(extrapolated) + "\n"
    if corrections:
        text += "\nSize of the correction a grey-box learns, |f_phi| / (|f_p| + |f_phi|) along its solves (components.json):\n\n"
        text += "| case | on f_p (first round) | on the augmented physics |\n|---|---|---|\n" + "\n".join(corrections) + "\n"
    return text.replace("|velocity|", "\\|velocity\\|")


KEPT = ("report.json", "report.md", "wall_time.json", "extrapolation.json", "correction_after.json")
START, END = "<!-- table: scripts/discovery_benchmark.py --table -->", "<!-- end table -->"


def keep(out: Path, results: Path) -> None:
    """The small result files of every finished run under ``out`` into ``results`` (same layout), for committing."""
    for path in out.rglob("*"):
        if path.name in KEPT and path.is_file():
            target = results / path.relative_to(out)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(path.read_bytes())


def _named(t: dict, report: dict) -> str:
    """A named term with its interval and spread, the alternatives the measurements cannot tell it from, and the terms
    it moves with that its run's evidence did not weigh it against."""
    interval = f" [{t['interval'][0]:.4g}, {t['interval'][1]:.4g}]" if t.get("interval") else ""
    alike = [
        f"{a['alternative']} {a['alternative_coefficient']:.4g} ({a['standard_errors']:+.1f} SE)"
        for entry in report["ambiguous"] if (entry["feature"], entry["component"]) == (t["feature"], t["component"])
        for a in entry["alternatives"]
    ]  # fmt: skip
    named = f"{t['name']}: {t['feature']} on d{t['component']}/dt {t['coefficient']:.4g}{interval}{_spread(t['distribution'])}"
    unweighed = _unweighed(t, report)
    named += f", or alike: {', '.join(alike)}" if alike else ""
    return named + (f", not weighed against: {unweighed}" if unweighed else "")


def _unweighed(t: dict, report: dict) -> str:
    """The terms a named term moves with (its regression's confusable pairs) that the run's evidence holds no
    comparison with."""
    named = {(n["feature"], n["component"]) for n in report["terms"]}
    weighed = {frozenset({e["feature"], e["alternative"]}) for e in report["evidence"] if e["component"] == t["component"]}
    pairs = [p for s in report["regression"] if s["component"] == t["component"] for p in s["confusable_pairs"]]
    partners = [p["b"] if p["a"] == t["feature"] else p["a"] for p in pairs if t["feature"] in (p["a"], p["b"])]
    return ", ".join(
        other for other in partners if (other, t["component"]) not in named and frozenset({t["feature"], other}) not in weighed
    )


def _spread(distribution: dict | None) -> str:
    """The fitted distribution of a coefficient that varies between trajectories, e.g. ", varies: U(low, high)"."""
    return f", varies: {distribution_text(distribution)}" if distribution else ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder of the runs (created; finished runs are kept)")
    parser.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES), help="cases to run")
    parser.add_argument("--seeds", nargs="*", type=int, default=[0], help="seeds of each case")
    parser.add_argument("--noise", type=float, default=0.0, help="Gaussian measurement noise, as a share of the data's std")
    parser.add_argument("--table", type=Path, help="only gather the finished runs into this Markdown file")
    parser.add_argument("--keep", type=Path, help="copy the finished runs' result files (reports, timings) into this folder")
    parser.add_argument("--doc", type=Path, help="only rewrite the table between the markers of this page (from --out)")
    parser.add_argument("--refit", action="store_true", help="also train a grey-box on each found augmented physics")
    args = parser.parse_args()
    args.out = args.out.resolve()  # each run's subprocess works inside its own folder
    if args.table:
        args.table.write_text(table(args.out))
        print(f"wrote {args.table}")
        return
    if args.doc:
        write_between(args.doc, START, END, table(args.out))
        print(f"rewrote the table in {args.doc}")
        return
    for case in args.cases:
        for seed in args.seeds:
            run_case(case, seed, args.noise, args.out, args.refit)
    if args.keep:
        keep(args.out, args.keep)


if __name__ == "__main__":
    main()
