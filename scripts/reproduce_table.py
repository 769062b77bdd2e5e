"""The paper's Table 1 from otgb's own code: {OT, WGAN} x {grey-box, black-box} x tasks x seeds.

    python scripts/reproduce_table.py --out bench/table                        # every task, seeds 0 1 2
    python scripts/reproduce_table.py --out bench/table --tasks Pendulum-1-m Adv-diff-1-m --seeds 0 1 2
    python scripts/reproduce_table.py --out bench/table --gather docs/results.md   # only write the table
    python scripts/reproduce_table.py --out bench/b --tasks Adv-diff-m-m --gather docs/results.md   # only that task's
    python scripts/reproduce_table.py --out /tmp/quick --quick --gather /tmp/quick/results.md   # minutes
    python scripts/reproduce_table.py --out bench/table --tasks React-diff-1-m -- --trainer.accelerator=gpu

Each run is ``otgb fit`` with the task's config and the method's overlays
(``configs/baselines/*.yaml``) and ``--seed_everything S``, then ``otgb test`` on its best
checkpoint; its test ``metrics.json`` is what the table gathers. Per task, two rows with nothing
to learn are scored by the same ``otgb test``: "f_p only" (:class:`otgb.models.IdentityMap`) and
"complete physics" (:class:`otgb.models.CompletePhysicsMap`: the DGP's simulator at the
training solver's step); the Reference row is the test's measured-half-against-half floor.

Interrupted? Run the same command again: finished runs (a test ``metrics.json``) are skipped,
an unfinished fit resumes from its ``last.ckpt``. The budgets are the task configs' own (sized
for 2 CPU cores; the paper's are larger, see each config's header); ``--quick`` trains 4 steps
on small sets, to check the whole path, not to measure anything.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import yaml

from otgb.command import logger_override
from otgb.reports import mean_spread
from otgb.runs import machine, newest

ROOT = Path(__file__).parents[1]
BASELINES = ROOT / "configs" / "baselines"
# paper name -> (config stem, black-box overlay, one-to-one)
TASKS = {
    "Pendulum-1-m": ("pendulum", "lstm", True),
    "Pendulum-2-m": ("pendulum_2m", "lstm", False),
    "Pendulum-m-m": ("pendulum_mm", "lstm", False),
    "Adv-diff-1-m": ("advdiff", "resnet1d", True),
    "Adv-diff-m-m": ("advdiff_mm", "resnet1d", False),
    "React-diff-1-m": ("reactdiff", "unet3d", True),
}
METHODS = ("OT-GB", "WGAN-GB", "OT-BB", "WGAN-BB")
# The paper's Table 1 (../shared/REFERENCE.md): one-to-one N-RMSE / ABS ERR, one-to-many MMD / C2ST.
ONE_TO_ONE_PAPER = {  # N-RMSE, ABS ERR of OT-GB, WGAN-GB, OT-BB, WGAN-BB
    "Pendulum-1-m": [(0.0096, 0.0066), (0.0143, 0.0083), (0.0887, 0.050), (0.41, 0.2897)],
    "Adv-diff-1-m": [(0.0217, 0.0171), (0.0200, 0.0165), (0.0528, 0.0387), (0.0340, 0.0277)],
    "React-diff-1-m": [(0.0355, 0.0328), (0.0312, 0.0330), (0.0705, 0.0724), (0.1109, 0.1083)],
}
ONE_TO_MANY_PAPER = {  # MMD, C2ST of OT-GB, WGAN-GB, OT-BB, WGAN-BB, Reference
    "Pendulum-2-m": [(0.010, 0.72), (0.024, 0.89), (0.078, 0.94), (0.124, 0.98), (0.016, 0.51)],
    "Pendulum-m-m": [(0.011, 0.77), (0.022, 0.87), (0.029, 0.99), (1.064, 0.99), (0.011, 0.51)],
    "Adv-diff-m-m": [(0.0396, 0.57), (0.0430, 0.73), (0.0512, 0.74), (0.131, 0.99), (0.0081, 0.50)],
}
PAPER = {task: dict(zip((*METHODS, "Reference"), rows)) for task, rows in {**ONE_TO_ONE_PAPER, **ONE_TO_MANY_PAPER}.items()}
QUICK = [
    "--trainer.max_steps=4",
    "--trainer.val_check_interval=2",
    "--data.batch_size=4",
    "--data.n_measured=24",
    "--data.n_val=12",
    "--data.n_test=12",
    "--evaluation.reference_repeats=1",
    "--evaluation.c2st_folds=2",
    "--components.enabled=false",
]
TABLE_START, TABLE_END = "<!-- table1: scripts/reproduce_table.py -->", "<!-- end table1 -->"


def configs(task: str, method: str) -> list[str]:
    """``--config`` arguments of a method on a task: the task's config, then the method's overlays."""
    stem, black_box, _ = TASKS[task]
    files = [ROOT / "configs" / f"{stem}.yaml"]
    files += [BASELINES / f"{black_box}.yaml"] if method.endswith("BB") else []
    files += [BASELINES / "wgan.yaml"] if method.startswith("WGAN") else []
    return [arg for path in files for arg in ("--config", str(path))]


def otgb(args: list[str], log: Path, on_exit: Callable[[float], None] = lambda seconds: None) -> None:
    """``otgb <args>`` with its output in ``log``; ``on_exit`` gets its wall time in seconds, even if it failed (then exits)."""
    start = time.perf_counter()
    with open(log, "a") as out:
        done = subprocess.run([sys.executable, "-m", "otgb.cli", *args], stdout=out, stderr=subprocess.STDOUT)
    on_exit(time.perf_counter() - start)
    if done.returncode != 0:
        sys.exit(f"otgb {args[0]} failed (exit {done.returncode}); its output: {log}")


def add_fit_time(folder: Path, extra: list[str]) -> Callable[[float], None]:
    """Adds a fit's (or an interrupted fit's) seconds to the run's ``wall_time.json``."""

    def add(seconds: float) -> None:
        path = folder / "wall_time.json"
        timing = json.loads(path.read_text()) if path.exists() else {"fit_s": 0.0}
        path.write_text(json.dumps({**timing, "fit_s": timing["fit_s"] + seconds, "machine": machine(asks_for_gpu(extra))}))

    return add


def run_method(out: Path, task: str, method: str, seed: int, extra: list[str]) -> None:
    """Fit (or resume) and test one method on one task with one seed, unless its test is done."""
    folder = out / task / method / f"seed{seed}"
    if metrics(folder) is not None:
        return
    folder.mkdir(parents=True, exist_ok=True)
    common = [*configs(task, method), f"--seed_everything={seed}", "--trainer.enable_progress_bar=false", *extra]
    last = newest(folder / "fit", "version_*/checkpoints/last.ckpt")  # a resumed fit writes the next version
    resume = [f"--ckpt_path={last}"] if last is not None else []
    print(f"{task} {method} seed {seed}: {'resuming' if resume else 'fitting'}", flush=True)
    otgb(["fit", *common, logger_override(str(folder), "fit"), *resume], folder / "otgb.log", add_fit_time(folder, extra))
    best = newest(folder / "fit", "version_*/checkpoints/best-*.ckpt")  # the resumed fit's only if it beat the earlier best
    otgb(["test", *common, logger_override(str(folder), "test"), f"--ckpt_path={best}"], folder / "otgb.log")


def run_fixed(out: Path, task: str, extra: list[str]) -> None:
    """The two rows with nothing to learn: f_p only and complete physics, scored by ``otgb test``."""
    stem = TASKS[task][0]
    hidden = yaml.safe_load((ROOT / "configs" / f"{stem}.yaml").read_text())["data"]["hidden_effect"]
    maps = {
        "f_p only": ["--model.transport_map=otgb.models.IdentityMap"],
        "complete physics": [
            "--model.transport_map=otgb.models.CompletePhysicsMap",
            f"--model.transport_map.init_args.hidden_effect={json.dumps(hidden)}",
        ],
    }
    for name, args in maps.items():
        folder = out / task / name.replace(" ", "_")
        if metrics(folder) is not None:
            continue
        folder.mkdir(parents=True, exist_ok=True)
        print(f"{task} {name}", flush=True)
        args = [*configs(task, "OT-GB"), *args, "--trainer.enable_progress_bar=false", *extra]
        otgb(["test", *args, logger_override(str(folder), "test")], folder / "otgb.log")


def asks_for_gpu(extra: list[str]) -> bool:
    return any(arg.replace(" ", "") in ("--trainer.accelerator=gpu", "--trainer.accelerator=cuda") for arg in extra)


def metrics(folder: Path) -> dict | None:
    """The test report of a run folder (None before its test has finished)."""
    report = newest(folder, "test/version_*/metrics.json")
    return json.loads(report.read_text()) if report is not None else None


def seeds_cell(values: list[float]) -> str:
    return mean_spread(values, plus="+-", empty="-")


def task_table(out: Path, task: str) -> list[str]:
    """Markdown rows of one task: each method over its seeds, f_p only, complete physics, Reference; the paper beside."""
    one_to_one = TASKS[task][2]
    names = ("nrmse", "abs_err") if one_to_one else ("mmd", "c2st")
    head = "N-RMSE | ABS ERR" if one_to_one else "MMD | C2ST"
    machines = sorted({json.loads(p.read_text())["machine"] for p in (out / task).glob("*/seed*/wall_time.json")})
    lines = [f"**{task}** (`configs/{TASKS[task][0]}.yaml`; fitted on {' and '.join(machines) or '-'})", ""]
    lines += [f"| row | seeds | {head} | paper | wall time per fit |", "|---|---|---|---|---|---|"]
    paper = PAPER.get(task, {})
    for method in METHODS:
        runs = [(m, f) for f in sorted((out / task / method).glob("seed*")) if (m := metrics(f)) is not None]
        values = [[m["model"][name]["mean"] for m, _ in runs] for name in names]
        walls = [json.loads((f / "wall_time.json").read_text())["fit_s"] for _, f in runs]
        published = " / ".join(f"{v}" for v in paper[method]) if method in paper else "-"
        wall = f"{statistics.mean(walls) / 60:.1f} min" if walls else "-"
        lines.append(f"| {method} | {len(runs)} | {seeds_cell(values[0])} | {seeds_cell(values[1])} | {published} | {wall} |")
    fixed = {name: metrics(out / task / name.replace(" ", "_")) for name in ("f_p only", "complete physics")}
    for name, m in fixed.items():
        cells = " | ".join(seeds_cell([m["model"][k]["mean"]] if m else []) for k in names)
        lines.append(f"| {name} | - | {cells} | - | - |")
    reference = next((m["reference"] for m in fixed.values() if m is not None), None)
    ref_cells = " | ".join(seeds_cell([reference[k]["mean"]] if reference else []) for k in names)
    published = " / ".join(map(str, paper["Reference"])) if "Reference" in paper else "-"
    lines.append(f"| Reference | - | {ref_cells} | {published} | - |")
    return lines


def gather(out: Path, tasks: list[str], target: Path) -> None:
    """Write the tables of ``tasks`` between the markers of ``target`` (appended with them if they are missing).

    Only the named tasks' tables are rewritten from the runs under ``out``; another task's table
    already in ``target`` is kept as it is (its runs may live in another folder or on another machine).
    """
    text = target.read_text() if target.exists() else ""
    kept = {}
    if TABLE_START in text and TABLE_END in text:
        before, rest = text.split(TABLE_START, 1)
        section, after = rest.split(TABLE_END, 1)
        kept = task_blocks(section)
    else:
        before, after = text + ("\n" if text else ""), "\n"
    blocks = {**kept, **{task: "\n".join(task_table(out, task)) for task in tasks}}
    lines = [TABLE_START, ""] + [line for task in TASKS if task in blocks for line in (blocks[task], "")] + [TABLE_END]
    target.write_text(before + "\n".join(lines) + after)
    print(f"wrote {target}")


def task_blocks(section: str) -> dict[str, str]:
    """The tables of a written section by task: a ``**task**`` heading and the table rows that follow it."""
    blocks: dict[str, list[str]] = {}
    current = None
    for line in section.splitlines():
        heading = line.split("**")[1] if line.startswith("**") else None
        if heading in TASKS:
            current = blocks.setdefault(heading, [line, ""])
        elif current is not None and line.startswith("|"):
            current.append(line)
        elif line.strip():
            current = None
    return {task: "\n".join(lines) for task, lines in blocks.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder of the runs (finished runs are kept)")
    parser.add_argument("--tasks", nargs="*", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    parser.add_argument("--quick", action="store_true", help="4 training steps on small sets: checks the path, measures nothing")
    parser.add_argument(
        "--gather", type=Path, help="write the tables of --tasks from the finished runs into this Markdown file (others kept)"
    )
    parser.add_argument(
        "--fixed",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also score the f_p-only and complete-physics rows (--no-fixed: several methods in parallel)",
    )
    parser.add_argument("overrides", nargs="*", help="otgb overrides for every run, after --, e.g. -- --trainer.accelerator=gpu")
    args = parser.parse_args()
    out = args.out.resolve()
    if args.gather is None or args.quick:
        extra = [*(QUICK if args.quick else []), f"--data.cache_dir={out / 'cache'}", *args.overrides]
        for task in args.tasks:
            if args.fixed:
                run_fixed(out, task, extra)
            for seed in args.seeds:
                for method in args.methods:
                    run_method(out, task, method, seed, extra)
    if args.gather is not None:
        gather(out, args.tasks, args.gather)


if __name__ == "__main__":
    main()
