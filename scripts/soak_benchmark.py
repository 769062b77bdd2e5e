"""Load and soak: simulations per second, memory over time, and a SIGKILL followed by a resume.

``soak`` trains ``configs/pendulum_mm.yaml`` (one-to-many pendulum) on ``--budget`` simulations
(the paper's 4e6 by default) with ``otgb fit``, samples the resident memory of the whole process
group (every process of a DDP run) every ``--sample-s`` seconds into ``memory.csv`` (with
``--accelerator gpu`` also the GPU memory in use, from ``nvidia-smi``), and, with
``--kill-after S``, SIGKILLs the group at a random moment in [S/2, S] (seeded; later if no
``last.ckpt`` exists yet) and resumes from the newest ``last.ckpt`` until the budget is spent. ``soak.json`` then says:

- simulations per second (training only, from ``val/simulations`` and ``val/wall_time_s``);
- memory: resident MB (and GPU MB) at the start, end and peak of each half of the run (growth = a leak),
  drawn over time into ``memory.png``;
- whether the resume lost simulations (the final step count against budget / simulations per
  step) or log rows (every logged step of the run, 0 to the end, in some ``metrics.csv``).

``throughput`` trains ``--config`` (``configs/pendulum.yaml``) for ``--steps`` steps in each of
``--runs``, one after another on the same machine: 1 process, 2 DDP processes (the same
simulations), 1 GPU; ``--cpus N`` pins every run to N CPUs, so a GPU machine with many cores can
stand in for a 2-core one. It reports simulations per second of each.

Both skip what is done and resume what is not: run the same command again after an interruption.
Linux only (memory is read from /proc).

    python scripts/soak_benchmark.py soak --out bench/soak --kill-after 600
    python scripts/soak_benchmark.py soak --out bench/soak-gpu --accelerator gpu --devices 2
    python scripts/soak_benchmark.py throughput --out bench/throughput --steps 200
    python scripts/soak_benchmark.py throughput --out bench/gpu --config reactdiff.yaml --runs cpu:1 gpu:1 --cpus 2 --steps 40
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch
import yaml

from otgb.runs import newest

ROOT = Path(__file__).parents[1]


def fit_command(config: str, out: Path, extra: list[str]) -> list[str]:
    logger = f"--trainer.logger=[{{class_path: lightning.pytorch.loggers.CSVLogger, init_args: {{save_dir: {out}, name: run}}}}]"
    return [sys.executable, "-m", "otgb.cli", "fit", "--config", str(ROOT / "configs" / config), logger, *extra]


def group_rss_mb(pgid: int) -> float:
    """Resident memory (MB) of every process in process group ``pgid``, from /proc."""
    total = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[2]) == pgid:  # fields after the name: state, ppid, pgrp, ...
                total += int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, IndexError, ValueError):
            continue  # the process ended meanwhile
    return total / 2**20


def gpu_used_mb() -> float:
    """GPU memory in use (MB, summed over the machine's GPUs), from nvidia-smi."""
    query = ["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"]
    return sum(float(line) for line in subprocess.run(query, capture_output=True, text=True, check=True).stdout.split())


def run_sampled(command: list[str], out: Path, sample_s: float, kill_at: float | None, gpu: bool) -> tuple[int, float]:
    """Run ``command`` in its own process group, appending (time, host MB[, GPU MB]) rows to memory.csv; SIGKILL it at
    ``kill_at`` s."""
    start = time.time()
    with open(out / "fit.log", "a") as log, open(out / "memory.csv", "a", newline="") as memory:
        writer = csv.writer(memory)
        run = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        while run.poll() is None:
            writer.writerow([round(time.time(), 1), round(group_rss_mb(run.pid), 1), *([gpu_used_mb()] if gpu else [])])
            memory.flush()
            if kill_at is not None and time.time() - start > kill_at and newest_in_run(out, "last.ckpt") is not None:
                os.killpg(run.pid, signal.SIGKILL)
                run.wait()
                return -signal.SIGKILL, time.time() - start
            time.sleep(sample_s)
    return run.returncode, time.time() - start


def newest_in_run(out: Path, name: str) -> Path | None:
    return newest(out, f"run/version_*/**/{name}")


def soak(args: argparse.Namespace) -> None:
    if args.accelerator == "gpu" and shutil.which("nvidia-smi") is None:
        raise SystemExit("soak --accelerator gpu: nvidia-smi not found; it reads the GPU memory over time")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    extra = [
        f"--data.simulation_budget={args.budget}", f"--trainer.accelerator={args.accelerator}",
        f"--trainer.devices={args.devices}", "--trainer.enable_progress_bar=false", f"--seed_everything={args.seed}",
        *(["--trainer.strategy=ddp"] if args.devices > 1 else []), *args.overrides,
    ]  # fmt: skip
    state = json.loads((out / "state.json").read_text()) if (out / "state.json").exists() else {"killed": None, "runs": []}
    while not state["runs"] or state["runs"][-1]["returncode"] != 0:
        last = newest_in_run(out, "last.ckpt")
        kill_at = None
        if args.kill_after and state["killed"] is None:
            kill_at = random.Random(args.seed).uniform(args.kill_after / 2, args.kill_after)
        command = fit_command("pendulum_mm.yaml", out, extra) + ([f"--ckpt_path={last}"] if last else [])
        returncode, wall = run_sampled(command, out, args.sample_s, kill_at, args.accelerator == "gpu")
        if returncode == -signal.SIGKILL:
            state["killed"] = {"after_s": wall, "last_ckpt_before": str(last)}
        elif returncode != 0:
            raise SystemExit(f"otgb fit failed (exit {returncode}); see {out / 'fit.log'}")
        state["runs"].append({"returncode": returncode, "wall_s": wall, "resumed_from": str(last) if last else None})
        (out / "state.json").write_text(json.dumps(state, indent=1))
    (out / "soak.json").write_text(json.dumps(summarise(out, args, state), indent=1))
    memory_figure(out)
    print((out / "soak.json").read_text())


def summarise(out: Path, args: argparse.Namespace, state: dict) -> dict:
    rows = [row for path in sorted(out.glob("run/version_*/metrics.csv")) for row in csv.DictReader(open(path))]
    val = [(float(r["val/simulations"]), float(r["val/wall_time_s"])) for r in rows if r.get("val/wall_time_s")]
    last = torch.load(newest_in_run(out, "last.ckpt"), weights_only=False)
    config = yaml.safe_load(newest_in_run(out, "config.yaml").read_text())
    per_step = config["data"]["batch_size"] * config["model"]["t_max"] * args.devices
    steps = {int(float(r["step"])) for r in rows if r.get("train/simulations")}
    every = min((b - a for a, b in zip(sorted(steps), sorted(steps)[1:])), default=1)
    samples = list(csv.reader(open(out / "memory.csv")))
    half = len(samples) // 2
    return {
        "machine": f"{os.cpu_count()} CPUs, {args.accelerator} x {args.devices}",
        "budget": args.budget,
        "simulations_per_s": val[-1][0] / val[-1][1] if val else None,
        "final_global_step": last["global_step"],
        "expected_steps": args.budget // per_step,
        "simulations_counted": last["global_step"] * per_step,
        "log_rows_missing": sorted(set(range(min(steps), max(steps) + 1, every)) - steps) if steps else None,
        "memory_mb": halves([float(r[1]) for r in samples]) if half else None,
        "gpu_memory_mb": halves([float(r[2]) for r in samples]) if half and len(samples[0]) > 2 else None,
        "killed": state["killed"],
        "runs": state["runs"],
    }


def memory_figure(out: Path) -> None:
    """``memory.png``: host (and GPU) memory over the soak's wall time, from ``memory.csv``; a restart shows as a drop."""
    import matplotlib.pyplot as plt

    from otgb.analysis.figures import save  # switches matplotlib to its file backend

    samples = [[float(v) for v in row] for row in csv.reader(open(out / "memory.csv"))]
    minutes = [(row[0] - samples[0][0]) / 60 for row in samples]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(minutes, [row[1] / 1024 for row in samples], label="host, resident (process group)")
    if len(samples[0]) > 2:
        ax.plot(minutes, [row[2] / 1024 for row in samples], label="GPU, in use (nvidia-smi)")
    ax.set(xlabel="wall time (min)", ylabel="GiB", title=f"soak memory: {out.name}")
    ax.legend()
    fig.tight_layout()
    save(fig, out / "memory.png")
    plt.close(fig)


def halves(memory: list[float]) -> dict[str, list[float]]:
    """First and last sample of each half of a memory series, and each half's peak: growth between halves = a leak."""
    half = len(memory) // 2
    first, second = memory[:half], memory[half:]
    return {"first_half": [first[0], first[-1], max(first)], "second_half": [second[0], second[-1], max(second)]}


def cpu_name() -> str:
    """The CPU's model name, from /proc/cpuinfo."""
    lines = [line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("model name")]
    return lines[0].split(":", 1)[1].strip() if lines else "unknown CPU"


RUNS = {"cpu:1": "1 process", "cpu:2": "2 processes (DDP)", "gpu:1": "1 GPU"}


def run_spec(text: str) -> str:
    """``accelerator:processes`` (cpu:2, gpu:1) for ``--runs``."""
    accelerator, _, processes = text.partition(":")
    if accelerator not in ("cpu", "gpu") or not processes.isdigit() or int(processes) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected accelerator:processes, e.g. cpu:1, cpu:2 or gpu:1")
    return text


def throughput(args: argparse.Namespace) -> None:
    """Simulations per second of ``--config`` in each of ``--runs``, on the same simulations, one after another."""
    out = Path(args.out)
    results = json.loads((out / "throughput.json").read_text()) if (out / "throughput.json").exists() else {}
    pin = (lambda: os.sched_setaffinity(0, range(args.cpus))) if args.cpus else None
    env = {**os.environ, **({"OMP_NUM_THREADS": str(args.cpus)} if args.cpus else {})}
    for run in args.runs:
        accelerator, processes = run.split(":")[0], int(run.split(":")[1])
        name = f"{Path(args.config).stem}, {RUNS.get(run, run)}"
        if name in results:
            continue
        folder = out / name.replace(", ", "-").replace(" ", "_").replace("(", "").replace(")", "")
        folder.mkdir(parents=True, exist_ok=True)
        steps = args.steps // processes  # the same number of simulations
        extra = [f"--trainer.max_steps={steps}", f"--trainer.val_check_interval={steps}", "--trainer.enable_progress_bar=false",
                 f"--trainer.accelerator={accelerator}", f"--trainer.devices={processes}", "--components.enabled=false",
                 *(["--trainer.strategy=ddp"] if processes > 1 else []), *args.overrides]  # fmt: skip
        start = time.time()
        subprocess.run(fit_command(args.config, folder, extra), check=True, capture_output=True, preexec_fn=pin, env=env)
        rows = [r for r in csv.DictReader(open(newest_in_run(folder, "metrics.csv"))) if r.get("val/wall_time_s")]
        sims, seconds = float(rows[-1]["val/simulations"]), float(rows[-1]["val/wall_time_s"])
        results[name] = {"simulations": sims, "training_s": seconds, "simulations_per_s": sims / seconds,
                         "command_wall_s": time.time() - start, "cpus": args.cpus or os.cpu_count(),
                         "device": torch.cuda.get_device_name() if accelerator == "gpu" else cpu_name()}  # fmt: skip
        (out / "throughput.json").write_text(json.dumps(results, indent=1))
    print(json.dumps(results, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    s = commands.add_parser("soak")
    s.add_argument("--out", required=True)
    s.add_argument("--budget", type=int, default=4_000_000)
    s.add_argument("--accelerator", default="cpu")
    s.add_argument("--devices", type=int, default=1)
    s.add_argument("--kill-after", type=float, default=None, help="SIGKILL the run at a random moment in [S/2, S] seconds")
    s.add_argument("--sample-s", type=float, default=10.0)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("overrides", nargs="*", help="more otgb fit overrides, after --")
    t = commands.add_parser("throughput")
    t.add_argument("--out", required=True)
    t.add_argument("--steps", type=int, default=200, help="steps of a 1-process run (a 2-process run takes half)")
    t.add_argument("--config", default="pendulum.yaml", help="a config in configs/")
    t.add_argument("--runs", nargs="+", type=run_spec, default=["cpu:1", "cpu:2"], help="cpu:1 cpu:2 gpu:1 ...")
    t.add_argument("--cpus", type=int, default=None, help="pin every run to the first N CPUs (and N threads)")
    t.add_argument("overrides", nargs="*", help="more otgb fit overrides, after --")
    args = parser.parse_args()
    soak(args) if args.command == "soak" else throughput(args)


if __name__ == "__main__":
    main()
