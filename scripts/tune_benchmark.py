"""`otgb tune` measured: a study on Pendulum-1-m at a reduced budget, its best settings refitted at the full budget
against the hand-tuned config over seeds, and one worker against two on the same study size.

    python scripts/tune_benchmark.py study --out results/tune --simulations 40000   # 12 trials (resumable)
    python scripts/tune_benchmark.py refit --out results/tune --seeds 0 1 2   # best.yaml and pendulum.yaml, full budget
    python scripts/tune_benchmark.py workers --out bench/workers --trials 4 --simulations 16000   # 1 worker against 2
    python scripts/tune_benchmark.py table --out results/tune --doc docs/tune.md   # summary.md, and the docs' table

Every step resumes: the study is an Optuna study on disk, and a refit whose test report exists is skipped. Result
files (trials.md, best.yaml, refits.json, workers.json, summary.md) are small and meant to be committed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import optuna
import torch
from result_tables import header, listed, read_json, row, spaced

from otgb.reports import mean_spread, write_between
from otgb.runs import fit_and_test, machine, newest, run_otgb

ROOT = Path(__file__).parents[1]
CONFIG = ROOT / "configs" / "pendulum.yaml"
SPACE = ROOT / "configs" / "tune" / "pendulum.yaml"
FULL_BUDGET = 100_000  # configs/pendulum.yaml's budget: best.yaml holds the study's reduced one


def reduced(simulations: int) -> list[str]:
    """The overrides of a trial at a reduced budget."""
    return [f"--data.simulation_budget={simulations}", "--trainer.val_check_interval=125", "--trainer.enable_progress_bar=false"]


def study(out: Path, trials: int, simulations: int) -> None:
    out.mkdir(parents=True, exist_ok=True)
    args = ["tune", "--config", str(CONFIG), f"--tune.space={SPACE}", f"--tune.trials={trials}", *reduced(simulations)]
    seconds = run_otgb(args, out / "study.log", cwd=out)
    study_dir = out / "runs" / "tune-pendulum"
    for name in ("trials.md", "best.yaml", "history.png", "importances.png"):
        if (study_dir / name).exists():
            shutil.copy(study_dir / name, out / name)
    spent = read_json(out / "study.json").get("seconds", 0.0)
    record = {"seconds": spent + seconds, "trials": trials, "simulations": simulations, "machine": machine()}
    (out / "study.json").write_text(json.dumps(record))


def refit(out: Path, seeds: list[int]) -> None:
    """Per seed: best.yaml as it is (the study's budget: does its trial's score come back?), and best.yaml and the
    hand-tuned config at the full budget, each fitted and tested."""
    results = read_json(out / "refits.json")
    storage = f"sqlite:///{out / 'runs' / 'tune-pendulum' / 'study.db'}"
    results.setdefault("study_best", optuna.load_study(study_name="pendulum", storage=storage).best_value)
    runs = [("tuned-as-is", out / "best.yaml", []), ("tuned", out / "best.yaml", [f"--data.simulation_budget={FULL_BUDGET}"])]
    runs.append(("hand-tuned", CONFIG, [f"--data.simulation_budget={FULL_BUDGET}"]))
    for name, config, budget in runs:
        for seed in seeds:
            key = f"{name}-seed{seed}"
            if key in results:
                continue
            folder = out / "refit" / key
            report = fit_and_test(folder, ["--config", str(config), f"--seed_everything={seed}", *budget])
            best = newest(folder / "fit", "version_*/checkpoints/best-*.ckpt")
            ckpt = torch.load(best, map_location="cpu", weights_only=False)
            selection = float(next(v for k, v in ckpt["callbacks"].items() if "BestAndLastCheckpoint" in k)["best_model_score"])
            results[key] = {"abs_err": report["model"]["abs_err"]["mean"], "val_best": selection, "fit_s": report["fit_s"]}
            results[key]["machine"] = machine()
            (out / "refits.json").write_text(json.dumps(results, indent=1))


def workers(out: Path, trials: int, simulations: int) -> None:
    """The same study size run by one worker and by two, each from an empty folder, one after the other."""
    args = ["tune", "--config", str(CONFIG), f"--tune.space={SPACE}", f"--tune.trials={trials}", "--tune.pruner=none"]
    args += reduced(simulations)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    walls = {}
    for count in (1, 2):
        folder = out / f"{count}-workers"
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        started = time.time()
        command = [sys.executable, "-m", "otgb.cli", *args]
        running = [
            subprocess.Popen(command, cwd=folder, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for _ in range(count)
        ]
        codes = [p.wait() for p in running]
        if any(codes):
            raise SystemExit(f"tune_benchmark workers: exit statuses {codes} in {folder}")
        walls[count] = time.time() - started
        folders = sorted(p.name for p in (folder / "runs" / "tune-pendulum").glob("trial_*"))
        walls[f"{count}_trials"] = folders
    walls["ratio"] = walls[2] / walls[1]
    walls["simulations_per_trial"] = simulations
    walls["machine"] = machine()
    (out / "workers.json").write_text(json.dumps(walls, indent=1))
    print(f"1 worker {walls[1]:.0f} s, 2 workers {walls[2]:.0f} s: ratio {walls['ratio']:.2f}")


START, END = "<!-- results: scripts/tune_benchmark.py table -->", "<!-- end results -->"


def table(out: Path, doc: Path | None = None) -> None:
    """summary.md from the result files; with ``doc``, the same between that page's markers."""
    lines = ["# otgb tune on Pendulum-1-m", ""]
    if timing := read_json(out / "study.json"):
        minutes, each = timing["seconds"] / 60, spaced(timing.get("simulations", 16_000))
        lines += [f"Study: {timing['trials']} trials at {each} simulations each, {minutes:.0f} min ({timing['machine']}).", ""]
    if results := read_json(out / "refits.json"):
        trial = results.get("study_best")
        as_is = [v["val_best"] for k, v in results.items() if k.startswith("tuned-as-is-seed")]
        if as_is:
            against = f", against its trial's {trial:.4g}" if trial is not None else ""
            lines.append(f"best.yaml refitted as it is (the study's budget): best validation ABS ERR {mean_spread(as_is)}")
            lines += [f"over {len(as_is)} seeds ({listed(as_is)}){against}.", ""]
        lines += header(["config, full budget (1e5 simulations)", "seeds", "test ABS ERR, mean ± std", "per seed"])
        for name in ("tuned", "hand-tuned"):
            values = [v["abs_err"] for k, v in results.items() if k.startswith(f"{name}-seed")]
            label = "best.yaml (tuned)" if name == "tuned" else "configs/pendulum.yaml (hand-tuned)"
            lines.append(row([label, len(values), mean_spread(values) or "-", listed(values)]))
        lines.append("")
    if w := read_json(out / "workers.json"):
        size, per_trial = len(w["1_trials"]), w.get("simulations_per_trial", 3200)
        lines.append(
            f"Workers: the same {size}-trial study ({per_trial} simulations per trial) took {w['1']:.0f} s with one worker "
            f"and {w['2']:.0f} s with two"
        )
        lines += [f"(ratio {w['ratio']:.2f}; each worker 1 thread, {w['machine']}); trials run: {len(w['2_trials'])}.", ""]
    (out / "summary.md").write_text("\n".join(lines))
    print("\n".join(lines))
    if doc is not None:
        write_between(doc, START, END, "\n".join(lines[2:]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=["study", "refit", "workers", "table"])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--trials", type=int, default=12)
    parser.add_argument("--simulations", type=int, default=40_000, help="study and workers: simulations per trial")
    parser.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    parser.add_argument("--doc", type=Path, help="table: also write the results between this page's markers")
    args = parser.parse_args()
    out = args.out.resolve()
    steps = {
        "study": lambda: study(out, args.trials, args.simulations),
        "refit": lambda: refit(out, args.seeds),
        "workers": lambda: workers(out, args.trials, args.simulations),
        "table": lambda: table(out, args.doc),
    }
    steps[args.step]()


if __name__ == "__main__":
    main()
