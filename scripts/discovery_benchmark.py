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
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from otgb.data import generate_measured
from otgb.physics import AdvectionDiffusion, Constant, LibraryTerm, Pendulum, ReactionDiffusion, Uniform

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
    "pendulum_none": ("pendulum.yaml", Pendulum, [term("velocity", "velocity", Constant(0.0))], 1000, None, PENDULUM),
    "advdiff_advection": ("advdiff.yaml", AdvectionDiffusion, [term("d_s(T)", "T", Constant(-0.1))], 1000, None, ADVDIFF),
    "advdiff_decay": ("advdiff.yaml", AdvectionDiffusion, [term("T", "T", Constant(-0.5))], 1000, None, ADVDIFF),
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
        [],
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


def run_case(case: str, seed: int, noise: float, out: Path) -> None:
    folder = out / f"{case}{'-noise' if noise else ''}-seed{seed}"
    if list(folder.glob("runs/*/version_*/report.json")):
        print(f"{folder.name}: done, skipped")
        return
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
        *overrides,
    ]
    start = time.time()
    with open(folder / "discover.log", "w") as log:
        done = subprocess.run([sys.executable, "-m", "otgb.cli", *args], cwd=folder, stdout=log, stderr=subprocess.STDOUT)
    wall = time.time() - start
    (folder / "wall_time.json").write_text(json.dumps({"seconds": wall, "returncode": done.returncode, "machine": machine()}))
    print(f"{folder.name}: exit {done.returncode} in {wall / 60:.1f} min")


def machine() -> str:
    return f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, torch {torch.__version__}"


def truth_text(case: str) -> str:
    terms = CASES[case.split("-")[0]][2]
    return ", ".join(f"{t.feature} on d{t.component}/dt: {t.priors['coefficient']!r}" for t in terms)


def table(out: Path) -> str:
    rows = [
        "| case | seed | named (coefficient [95 %]) | truth | f_p C2ST | grey-box C2ST | augmented C2ST | Reference C2ST | wall time |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for folder in sorted(out.iterdir()):
        reports = sorted(folder.glob("runs/*/version_*/report.json"))
        if not reports:
            continue
        report = json.loads(reports[-1].read_text())
        case, seed = folder.name.rsplit("-seed", 1)
        named = "; ".join(_named(t) for t in report["terms"]) or "nothing"
        gap = report["gap"]
        c2st = lambda key: f"{gap[key]['c2st']:.3f}" if key in gap else "-"  # noqa: E731
        reference = f"{gap['reference']['c2st']:.3f} ± {gap['reference']['c2st_std']:.3f}"
        wall = (
            json.loads((folder / "wall_time.json").read_text())["seconds"] / 60
            if (folder / "wall_time.json").exists()
            else float("nan")
        )
        rows.append(
            f"| {case} | {seed} | {named} | {truth_text(case)} | {c2st('f_p')} | {c2st('greybox')} | {c2st('augmented')} | {reference} | {wall:.1f} min |"
        )
    return "\n".join(rows).replace("|velocity|", "\\|velocity\\|") + "\n"


def _named(t: dict) -> str:
    interval = f" [{t['interval'][0]:.3g}, {t['interval'][1]:.3g}]" if t.get("interval") else ""
    spread = f", {t['distribution']}" if t["distribution"] else ""
    return f"{t['name']}: {t['feature']} on d{t['component']}/dt {t['coefficient']:.4g}{interval}{spread}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder of the runs (created; finished runs are kept)")
    parser.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES), help="cases to run")
    parser.add_argument("--seeds", nargs="*", type=int, default=[0], help="seeds of each case")
    parser.add_argument("--noise", type=float, default=0.0, help="Gaussian measurement noise, as a share of the data's std")
    parser.add_argument("--table", type=Path, help="only gather the finished runs into this Markdown file")
    args = parser.parse_args()
    if args.table:
        args.table.write_text(table(args.out))
        print(f"wrote {args.table}")
        return
    for case in args.cases:
        for seed in args.seeds:
            run_case(case, seed, args.noise, args.out)


if __name__ == "__main__":
    main()
