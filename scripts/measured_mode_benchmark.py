"""Does the measured-data (marginal) mode select as well as the joint mode, and does it tell f_p apart?

Measurements are exported once from a config's DGP (``scripts/export_measured.py``, seed
``data.seed``, |Y| = ``data.n_measured``) and handed to otgb as a file, with the hidden effect
removed from the config: otgb is not told the effect. Two experiments:

``selection``: fit the config in joint mode (DGP known) and in marginal mode (the file), same
budget and seed, each keeping its best checkpoint on its own validation metric; then score
both selected checkpoints on the joint test set (``otgb test`` with the DGP config) and on the
file's held-out test part (``otgb test`` in marginal mode).

``separation``: for each config, ``otgb test`` in marginal mode with the untrained map, whose
report holds the f_p-alone and Reference rows of the marginal metrics.

``ignores-theta``: a file that recorded theta; its held-out test part against fresh DGP draws
for the recorded theta, and against DGP draws for theta drawn independently from the prior
(right marginal, wrong conditional: what a map that ignores theta produces), scored by the
marginal metrics and by the joint ones on (recorded theta, y), over 20 draw sets: the
rejection rate of MMDAgg is the test's level (right draws) or power (theta ignored).

``noise``: a file with white noise of sd ``--noise`` on every value; for each seed, a marginal fit
with ``data.measurement_noise`` given and one with it ignored (0), each best checkpoint scored
against the truth (the joint test set of the noise-free DGP: ABS ERR) and on the file's held-out
part with the noise given (marginal metrics); mean and spread over the seeds in ``noise.md``.

Each ``otgb fit`` and ``otgb test`` runs in this process (:func:`otgb.runs.load_run`). Every step is skipped when its
output exists, and an unfinished fit resumes from its ``last.ckpt``, so an interrupted benchmark is continued by
running the same command again.

    python scripts/measured_mode_benchmark.py selection --config configs/pendulum.yaml --out bench/pendulum
    python scripts/measured_mode_benchmark.py separation --config configs/*.yaml --out bench/separation
    python scripts/measured_mode_benchmark.py ignores-theta --config configs/pendulum.yaml --out bench/theta
    python scripts/measured_mode_benchmark.py noise --config configs/pendulum.yaml --out bench/noise --noise 0.1 --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from itertools import product
from pathlib import Path

from result_tables import header, row

from otgb.cli import closing_line
from otgb.command import logger_override
from otgb.data.seeding import generator_for
from otgb.metrics.joint import JointEvaluator
from otgb.reports import mean_spread, summary_of
from otgb.runs import load_run, newest

MARGINAL = ["--data.hidden_effect=[]"]
METRICS = ("abs_err", "nrmse", "mmd", "energy", "c2st", "mmdagg_reject")


def otgb(command: str, config: str, overrides: list[str], ckpt_path: Path | None) -> None:
    """``otgb fit`` (resumed from ``ckpt_path``) or ``otgb test`` (of ``ckpt_path``) in this process."""
    print("+ otgb", command, "--config", config, *overrides, *([f"--ckpt_path={ckpt_path}"] if ckpt_path else []), flush=True)
    run = load_run(config, *overrides)
    if command == "fit":
        run.trainer.fit(run.model, run.datamodule, ckpt_path=ckpt_path)
    else:
        run.trainer.test(run.model, run.datamodule, ckpt_path=ckpt_path, verbose=False)  # as otgb test: metrics.md has them
    folder = Path(run.trainer.loggers[0].log_dir)  # the command's last lines: the test's summary, the run directory
    if command == "test" and (sentence := summary_of(folder)):
        print(f"otgb test: {sentence}")
    print(closing_line(command, folder), flush=True)


def export(config: str, out: Path, record: list[str], noise: float = 0.0) -> Path:
    suffix = ("-" + "-".join(record) if record else "") + (f"-noise{noise:g}" if noise else "")
    path = out / f"measured-{Path(config).stem}{suffix}.npz"
    if not path.exists():
        script = Path(__file__).with_name("export_measured.py")
        command = [sys.executable, str(script), "--config", config, "--out", str(path), "--record", *record]
        subprocess.run([*command, "--noise", str(noise)], check=True)
    return path


def run_args(out: Path, name: str) -> list[str]:
    return [logger_override(str(out), name), f"--data.cache_dir={out / 'cache'}"]


def fit(out: Path, name: str, config: str, extra: list[str]) -> Path:
    """Fit (or resume, into the next version_N) run ``name``; return its best checkpoint."""
    done = out / name / "fit.done"
    if not done.exists():
        last = newest(out / name, "version_*/checkpoints/last.ckpt")
        otgb("fit", config, [*run_args(out, name), *extra], last)
        done.write_text("finished\n")
    return newest(out / name, "version_*/checkpoints/best-*.ckpt")


def test(out: Path, name: str, config: str, extra: list[str], ckpt: Path | None) -> dict:
    report = newest(out / name, "version_*/metrics.json")
    if report is None:
        otgb("test", config, [*run_args(out, name), *extra], ckpt)
        report = newest(out / name, "version_*/metrics.json")
    return json.loads(report.read_text())


def report_row(labels: list[str], report: dict, source: str = "model") -> str:
    """A row of ``labels`` and the report's figures of ``METRICS`` for ``source``."""
    cells = [report[source].get(m, {}).get("mean") for m in METRICS]
    return row([*labels, *("" if c is None else f"{c:.4g}" for c in cells)])


def selection(config: str, out: Path, extra: list[str]) -> None:
    measured = export(config, out, [])
    marginal = [*MARGINAL, f"--data.measured_path={measured}"]
    selected = {"joint": fit(out, "fit-joint", config, extra), "marginal": fit(out, "fit-marginal", config, [*extra, *marginal])}
    scored_on = {"joint": ("joint test set (DGP known)", extra), "heldout": ("held-out measurements", [*extra, *marginal])}
    lines = header(["selected by", "scored on", *METRICS])
    reports = {}
    for (mode, ckpt), (on, (where, args)) in product(selected.items(), scored_on.items()):
        reports[on] = test(out, f"test-{mode}-on-{on}", config, args, ckpt)
        lines.append(report_row([f"{mode} mode ({ckpt.name})", where], reports[on]))
    for on, (where, _) in scored_on.items():  # f_p and the Reference do not depend on the checkpoint
        lines += [report_row(["f_p alone", where], reports[on], "fp"), report_row(["Reference", where], reports[on], "reference")]
    (out / "selection.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def separation(configs: list[str], out: Path, extra: list[str]) -> None:
    lines = header(["config", "source", *METRICS])
    for config in configs:
        name = Path(config).stem
        measured = export(config, out, [])
        report = test(out, f"separation-{name}", config, [*extra, *MARGINAL, f"--data.measured_path={measured}"], None)
        lines += [report_row([name, "f_p alone"], report, "fp"), report_row([name, "Reference"], report, "reference")]
        (out / "separation.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def ignores_theta(config: str, out: Path, extra: list[str], repeats: int = 20) -> None:
    measured = export(config, out, ["theta"])
    dgp = load_run(config, *extra).datamodule.dgp
    data_module = load_run(config, *extra, *MARGINAL, f"--data.measured_path={measured}").datamodule
    data_module.setup("test")
    data = data_module.test_set
    n, shape = len(data["y"]), tuple(dgp.trajectory_shape)
    evaluators = {
        "marginal": JointEvaluator(shape, inputs=(), paired=False, mmdagg_permutations=500),
        "joint (theta, y)": JointEvaluator(shape, inputs=("theta",), paired=True, mmdagg_permutations=500),
    }
    scores: dict[tuple[str, str], list[dict]] = {}
    for repeat in range(repeats):  # fresh DGP draws each time: the rejection rate is the test's power (or level)
        g = generator_for("ignores-theta", repeat)
        x0, effect, other_theta = dgp.sample_initial_state(n, g), dgp.sample_effect_params(n, g), dgp.sample_theta(n, g)
        candidates = {
            "DGP, recorded theta": dgp.simulate(x0, data["theta"], effect),
            "DGP, theta ignored": dgp.simulate(x0, other_theta, effect),
        }
        for (label, draws), (kind, evaluator) in product(candidates.items(), evaluators.items()):
            scores.setdefault((label, kind), []).append(evaluator.evaluate(draws.unsqueeze(1), data, tests=True))
    lines = [
        f"{n} held-out test trajectories of {measured}; {repeats} independent draw sets per row",
        "",
        "| draws | metrics on | MMDAgg rejection rate | mean C2ST | mean energy |",
        "|---|---|---|---|---|",
    ]
    for (label, kind), runs in scores.items():
        mean = lambda key: sum(float(r[key]) for r in runs) / len(runs)  # noqa: E731,B023
        lines.append(f"| {label} | {kind} | {mean('mmdagg_reject'):.2f} | {mean('c2st'):.3f} | {mean('energy'):.4f} |")
    (out / "ignores-theta.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def noise(config: str, out: Path, extra: list[str], sd: float, seeds: list[int]) -> None:
    measured = export(config, out, [], sd)
    given = [*MARGINAL, f"--data.measured_path={measured}", f"--data.measurement_noise={sd}"]
    scores: dict[str, list[tuple[float, ...]]] = {}
    for seed, (label, fitted_with) in product(seeds, {"noise given": sd, "noise ignored": 0.0}.items()):
        seeded = [*extra, f"--seed_everything={seed}"]
        fitting = [*MARGINAL, f"--data.measured_path={measured}", f"--data.measurement_noise={fitted_with}"]
        name = f"{label.replace(' ', '-')}-seed{seed}"
        ckpt = fit(out, f"fit-{name}", config, [*seeded, *fitting])
        truth = test(out, f"truth-{name}", config, seeded, ckpt)["model"]
        heldout = test(out, f"heldout-{name}", config, [*seeded, *given], ckpt)
        model, floor = heldout["model"], heldout["reference"]
        figures = (truth["abs_err"]["mean"], model["c2st"]["mean"], model["energy"]["mean"], model["mmdagg_reject"]["mean"])
        scores.setdefault(label, []).append(figures)
        scores["Reference"] = [(float("nan"), floor["c2st"]["mean"], floor["energy"]["mean"], 0.0)]
    lines = [
        f"{measured.name}: white noise of sd {sd:g}; seeds {seeds}; ABS ERR against the noise-free DGP (joint test set),"
        " the rest on the held-out measurements with the noise given (the Reference: their two halves)",
        "",
        "| fitted with the measurements' noise | ABS ERR vs truth | C2ST | energy | MMDAgg rejects |",
        "|---|---|---|---|---|",
    ]
    for label, rows in scores.items():
        columns = [[r[k] for r in rows] for k in range(4)]
        cells = ["-" if any(math.isnan(v) for v in c) else mean_spread(c) for c in columns]  # "-": the Reference's ABS ERR
        lines.append(row([label, *cells[:3], f"{sum(columns[3]):.0f} of {len(rows)}"]))
    (out / "noise.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", choices=["selection", "separation", "ignores-theta", "noise"])
    parser.add_argument("--config", nargs="+", required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--noise", type=float, default=0.1, help="noise: the sd of the white noise on the measurements")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="noise: the seeds of the fits")
    args, extra = parser.parse_known_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.experiment == "selection":
        for config in args.config:
            selection(config, args.out / Path(config).stem if len(args.config) > 1 else args.out, extra)
    elif args.experiment == "separation":
        separation(args.config, args.out, extra)
    elif args.experiment == "noise":
        noise(args.config[0], args.out, extra, args.noise, args.seeds)
    else:
        ignores_theta(args.config[0], args.out, extra)


if __name__ == "__main__":
    main()
