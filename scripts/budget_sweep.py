"""Test error against the simulation budget and the batch, over seeds: does more compute give a better map?

    python scripts/budget_sweep.py run --out results/budget --name pendulum-3125-steps --config configs/pendulum.yaml \\
        --budgets 100000 300000 1000000 --steps 3125 --seeds 0 1 2
    python scripts/budget_sweep.py run --out results/budget --name pendulum-batch --config configs/pendulum.yaml \\
        --budgets 300000 --batches 32 64 128 256 512 --seeds 0 [-- OVERRIDES...]
    python scripts/budget_sweep.py study --out results/budget --name pendulum-budget-study \\
        --storage sqlite:///STUDY_DIR/study.db --study pendulum-budget --space configs/tune/pendulum-budget.yaml
    python scripts/budget_sweep.py merge --out results/budget --name pendulum-gpu --parts gpu-part-a gpu-part-b
    python scripts/budget_sweep.py average --out results/budget --sweep pendulum-3125-steps \
        --folders RUNS/pendulum-3125-steps/1000000/320/seed{0,1,2}
    python scripts/budget_sweep.py gap --out results/budget --sweep pendulum-3125-steps \
        --folders RUNS/pendulum-3125-steps/1000000/320/seed{0,1,2} [--inputs 4000]
    python scripts/budget_sweep.py table --out results/budget --doc docs/results.md

Each (budget, batch, seed) is one real ``otgb fit`` and an ``otgb test`` of its best checkpoint
(:func:`otgb.runs.fit_and_test`), in ``<out>/runs/<name>/...``. ``--steps S`` spreads each budget over S
training steps (batch = budget / S); ``--batches`` fixes the batch instead. Everything after ``--`` goes to
both commands (a learning rate, a schedule). Results go to ``<out>/<name>.json`` as each run ends; a
rerun skips what is done and resumes an interrupted fit from its ``last.ckpt``. Sweeps run side by side (one
GPU, several processes) each under its own name; ``merge`` joins them into one. ``table`` writes every
sweep's table into ``--doc`` between ``<!-- results: scripts/budget_sweep.py -->`` and
``<!-- end results -->``, with a line per ``otgb tune`` study that ``study`` recorded (its result files copied
beside the sweeps, a summary in ``<out>/<name>/study.json``) and per ``average``: one grey-box whose f_phi is the
mean of the f_phi of a sweep's seeds at one budget (each seed's best checkpoint), tested as each seed was, in
``<out>/averaged/``. If the seeds' errors were their own, the mean's error would fall as one over the square root
of their number; what it keeps is what the runs share. ``gap`` places each seed's map against the true map (the
configured DGP) in the objective's two parts, on fresh inputs: its transport cost, and how far its outputs are from
the DGP's (``<out>/gap/``): is a map short of the measured distribution, or preferred by the objective to the truth?
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import optuna
import torch
import yaml
from result_tables import header, listed, read_json, results_in, row, spaced
from torch import Tensor, nn

from otgb.data.measured import generate_joint
from otgb.metrics.energy import energy_distance
from otgb.metrics.errors import abs_err
from otgb.ot.costs import kernel_weak_cost
from otgb.reports import LABELS, mean_spread, write_between
from otgb.runs import asks_for_gpu, fit_and_test, load_run, machine, newest

START, END = "<!-- results: scripts/budget_sweep.py -->", "<!-- end results -->"


def runs(args: argparse.Namespace) -> list[tuple[int, int]]:
    """The (budget, batch) pairs of the sweep."""
    if args.steps:
        return [(budget, budget // args.steps) for budget in args.budgets]
    return [(budget, batch) for budget in args.budgets for batch in args.batches]


def sweep(args: argparse.Namespace) -> None:
    out = Path(args.out)
    path = out / f"{args.name}.json"
    results = read_json(path)
    for seed in args.seeds:
        for budget, batch in runs(args):
            key = f"{budget}/{batch}/seed{seed}"
            if "map_lr" in results.get(key, {}):
                continue
            settings = [f"--data.simulation_budget={budget}", f"--data.batch_size={batch}", *args.overrides]
            command = ["--config", args.config, f"--seed_everything={seed}", *settings]
            folder = out / "runs" / args.name / key
            report = fit_and_test(folder, command)
            ran_on = results.get(key, {}).get("machine", machine(gpu=asks_for_gpu(args.overrides)))
            results[key] = {
                "budget": budget, "batch": batch, "seed": seed, "overrides": args.overrides, "fit_s": report["fit_s"],
                **{f"{source}_{args.metric}": report[source][args.metric]["mean"] for source in ("model", "fp")},
                **learning_rates(folder), "machine": ran_on,
            }  # fmt: skip
            path.write_text(json.dumps(results, indent=1))
            print(f"{args.name} {key}: {args.metric} {results[key][f'model_{args.metric}']:.4g}", flush=True)


def merge(out: Path, name: str, parts: list[str]) -> None:
    """Sweeps run side by side under their own names (``parts``) as one sweep ``name``; the parts' files are removed.
    A missing part, a run in two parts, or an existing sweep ``name`` stops it with one line, nothing written."""
    missing = [part for part in parts if not (out / f"{part}.json").is_file()]
    if missing:
        raise SystemExit(f"budget_sweep.py merge: no result file for {missing} in {out}")
    if (out / f"{name}.json").exists():
        raise SystemExit(f"budget_sweep.py merge: {out / f'{name}.json'} exists; choose another --name")
    merged: dict = {}
    for part in parts:
        results = json.loads((out / f"{part}.json").read_text())
        if twice := sorted(set(results) & set(merged)):
            raise SystemExit(f"budget_sweep.py merge: {part} repeats runs {twice} of an earlier part")
        merged.update(results)
    (out / f"{name}.json").write_text(json.dumps(merged, indent=1))
    for part in parts:
        (out / f"{part}.json").unlink()
    print(f"{name}: {len(merged)} runs from {len(parts)} parts")


class MeanCorrection(nn.Module):
    """f_phi as the mean of several runs' f_phi."""

    def __init__(self, corrections: list[nn.Module]) -> None:
        super().__init__()
        self.corrections = nn.ModuleList(corrections)

    def forward(self, state: Tensor, cond: Tensor) -> Tensor:
        return torch.stack([correction(state, cond) for correction in self.corrections]).mean(0)


def seed_runs(out: Path, sweep_name: str, folders: list[Path], scratch: str, command: str) -> tuple[dict, list[str], list]:
    """The sweep's records, the folders' keys in it and a run per folder with its best checkpoint loaded (its logs
    written under ``scratch``, nothing into the runs); a folder that is not a finished run of the sweep stops it."""
    if not (out / f"{sweep_name}.json").is_file():
        raise SystemExit(f"budget_sweep.py {command}: no result file {out / f'{sweep_name}.json'} for --sweep {sweep_name}")
    recorded = json.loads((out / f"{sweep_name}.json").read_text())
    keys = ["/".join(folder.parts[-3:]) for folder in folders]
    if len({key.rsplit("/", 1)[0] for key in keys}) != 1 or not set(keys) <= set(recorded):
        raise SystemExit(f"budget_sweep.py {command}: {keys} are not seeds of one budget and batch of {sweep_name}")
    fits = [(newest(f / "fit", "version_*/config.yaml"), newest(f / "fit", "version_*/checkpoints/best-*.ckpt")) for f in folders]
    if missing := [str(f) for f, (config, best) in zip(folders, fits) if config is None or best is None]:
        raise SystemExit(f"budget_sweep.py {command}: no finished fit (its config.yaml and best checkpoint) in {missing}")
    overrides = lambda index: ["--trainer.logger=false", f"--trainer.default_root_dir={Path(scratch) / str(index)}"]  # noqa: E731
    return recorded, keys, [load_run(config, *overrides(i), ckpt_path=best) for i, (config, best) in enumerate(fits)]


def write_result(out: Path, kind: str, sweep_name: str, first: dict, result: dict) -> Path:
    path = out / kind / f"{sweep_name}-{first['budget']}-{first['batch']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"sweep": sweep_name, "budget": first["budget"], "batch": first["batch"]} | result, indent=1))
    return path


def average(out: Path, sweep_name: str, folders: list[Path]) -> None:
    """Test each seed's best checkpoint as ``otgb test`` did, then one grey-box with the mean of their f_phi; the
    seeds' figures must equal the sweep's, or the folders are not its runs."""
    with tempfile.TemporaryDirectory() as scratch:
        recorded, keys, runs = seed_runs(out, sweep_name, folders, scratch, "average")
        per_seed = [test_abs_err(run) for run in runs]
        for key, value in zip(keys, per_seed):
            if abs(value - recorded[key]["model_abs_err"]) > 1e-6:
                raise SystemExit(f"budget_sweep.py average: {key} tests to {value:.6g}, the sweep recorded another figure")
        runs[0].model.evaluation_map().correction = MeanCorrection([run.model.evaluation_map().correction for run in runs])
        averaged = test_abs_err(runs[0])
    result = {"keys": keys, "per_seed": per_seed, "averaged": averaged, "machine": machine()}
    path = write_result(out, "averaged", sweep_name, recorded[keys[0]], result)
    print(f"{path}: averaged f_phi {averaged:.4g}; seeds {mean_spread(per_seed)}")


def gap(out: Path, sweep_name: str, folders: list[Path], n: int) -> None:
    """Where each seed's map sits against the true map, in the two parts of the objective (paper, eq. kernel-maximin):
    on ``n`` fresh inputs, its transport cost (the run's own C_hat) beside the true map's (the configured DGP), and
    the energy distance of its outputs to the DGP's outputs for ``n`` other inputs beside the true map's own (its
    noise floor; its spread over 20 random halves of the DGP's outputs). A map that the objective prefers to the truth
    costs less at an equal distance."""
    if n < 2:
        raise SystemExit(f"budget_sweep.py gap: --inputs {n}: expected at least 2 (a distance between samples needs two each)")
    with tempfile.TemporaryDirectory() as scratch:
        recorded, keys, runs = seed_runs(out, sweep_name, folders, scratch, "gap")
        source = runs[0].datamodule.source
        if source.pointwise_process is None:
            raise SystemExit(f"budget_sweep.py gap: {sweep_name} has no deterministic configured DGP to be the true map")
        fresh = generate_joint(source.physics, source.pointwise_process, 2 * n, 1, source.seed, "gap")
        x, x0, theta = fresh["x"][:n], fresh["x0"][:n], fresh["theta"][:n]
        truth, others = fresh["y"][:n, 0], fresh["y"][n:, 0].flatten(1)
        objective = runs[0].model.objective
        if not hasattr(objective, "kernel"):
            raise SystemExit(f"budget_sweep.py gap: {sweep_name} trains with {objective!r}, which has no transport cost")
        cost = lambda y: kernel_weak_cost(x, y[:, None], 0.0, objective.kernel)  # noqa: E731
        distance = lambda y: energy_distance(y.flatten(1), others).item()  # noqa: E731
        with torch.no_grad():
            maps = [run.model.generate(x, x0, theta, 1)[:, 0] for run in runs]
    differences = [cost(y) - cost(truth) for y in maps]  # per input: the standard error of the mean difference
    result = {"keys": keys, "inputs": n, "objective": repr(objective), "true_cost": cost(truth).mean().item()}
    result |= {"cost_minus_true": [d.mean().item() for d in differences]}
    result |= {"cost_minus_true_se": [d.std().item() / n**0.5 for d in differences]}
    result |= {"true_energy": distance(truth), "energy": [distance(y) for y in maps]}
    pooled, g = torch.cat([truth.flatten(1), others]), torch.Generator().manual_seed(0)
    halves = [pooled[torch.randperm(2 * n, generator=g)].chunk(2) for _ in range(20)]
    result |= {"null_energy_sd": torch.stack([energy_distance(a, b) for a, b in halves]).std().item()}
    result |= {"abs_err": [abs_err(y, truth).mean().item() for y in maps], "machine": machine()}
    path = write_result(out, "gap", sweep_name, recorded[keys[0]], result)
    print(f"{path}: transport cost minus the true map's {result['cost_minus_true']}; energy {result['energy']}")


def test_abs_err(run) -> float:
    return run.trainer.test(run.model, datamodule=run.datamodule, verbose=False)[0]["test/abs_err"]


def averaged_lines(out: Path) -> list[str]:
    """A line per ``average`` result in ``out``."""
    return [
        f"- `{r['sweep']}` at {spaced(r['budget'])} simulations, batch {r['batch']}: one grey-box with the mean of its "
        f"{len(r['per_seed'])} seeds' f_phi has test ABS ERR {r['averaged']:.4g}; the seeds alone "
        f"{mean_spread(r['per_seed'])} ({listed(r['per_seed'])}). {r['machine']}."
        for r in results_in(out, "averaged/*.json").values()
    ]


def gap_lines(out: Path) -> list[str]:
    """A table of every ``gap`` result in ``out``: a row for the true map, then one per seed."""
    lines = [
        "", "Each seed's map against the true map (`gap`), on fresh inputs: its transport cost minus the true map's (± the "
        "standard error over the inputs) and the energy distance of its outputs to the DGP's for as many other inputs (unbiased, "
        "on pooled-standardised values: 0 on average for equal distributions; for the true map, the noise, with its sd over "
        "random halves of the DGP's outputs).", "",
        *header(["sweep", "budget", "batch", "map", "inputs", "ABS ERR", "transport cost minus the true map's",
                 "energy distance"]),
    ]  # fmt: skip
    for r in results_in(out, "gap/*.json").values():
        first = [r["sweep"], spaced(r["budget"]), r["batch"]]
        noise = f"{r['true_energy']:.2g} ± {r['null_energy_sd']:.2g}"
        lines.append(row([*first, f"true map (cost {r['true_cost']:.4g})", r["inputs"], "0", "0", noise]))
        for key, err, d, se, energy in zip(r["keys"], r["abs_err"], r["cost_minus_true"], r["cost_minus_true_se"], r["energy"]):
            lines.append(row([*first, key.rsplit("/", 1)[1], r["inputs"], f"{err:.4g}", f"{d:+.4f} ± {se:.4f}", f"{energy:.2g}"]))
    return lines if len(lines) > 5 else []


def learning_rates(folder: Path) -> dict[str, float]:
    """The map's and the critic's learning rates as trained (before any schedule: a scheduler's ``initial_lr``), from
    the fit's last checkpoint."""
    ckpt = torch.load(newest(folder / "fit", "version_*/checkpoints/last.ckpt"), map_location="cpu", weights_only=False)
    map_lr, critic_lr = (state["param_groups"][0] for state in ckpt["optimizer_states"])
    return {"map_lr": map_lr.get("initial_lr", map_lr["lr"]), "critic_lr": critic_lr.get("initial_lr", critic_lr["lr"])}


def record_study(out: Path, storage: str, study_name: str, space: str) -> None:
    """An ``otgb tune`` study's summary (study.json) and its files (trials.md, best.yaml, plots) in ``out``."""
    study = optuna.load_study(study_name=study_name, storage=storage)
    trials = study.get_trials(deepcopy=False)
    states = [t.state.name.lower() for t in trials]
    best = study.best_trial
    out.mkdir(parents=True, exist_ok=True)
    folder = Path(storage.removeprefix("sqlite:///")).parent
    for name in ("trials.md", "best.yaml", "history.png", "importances.png"):
        shutil.copy(folder / name, out / name)
    summary = {
        "study": study_name, "space": space, "monitor": study.user_attrs["monitor"], "trials": len(trials),
        "states": {s: states.count(s) for s in sorted(set(states))},
        "best_trial": best.number, "best_value": best.value, "best_params": best.params,
        "first_value": trials[0].value, "minutes": sum((t.duration.total_seconds() for t in trials if t.duration), 0.0) / 60,
    }  # fmt: skip
    data = yaml.safe_load((out / "best.yaml").read_text())["data"]
    summary.update(simulations=data["simulation_budget"], batch=data["batch_size"])
    (out / "study.json").write_text(json.dumps(summary, indent=1))


def study_lines(out: Path) -> list[str]:
    """A line per recorded study in ``out``: its size, its best trial and the config's own (trial 0)."""
    lines = []
    for path, s in results_in(out, "*/study.json").items():
        states = ", ".join(f"{n} {state}" for state, n in sorted(s["states"].items()))
        best = ", ".join(f"`{key}` {value:.4g}" for key, value in s["best_params"].items())
        size = spaced(s["simulations"])
        lines.append(
            f"- `otgb tune` study `{s['study']}` over `{s['space']}` at {size} simulations, batch {s['batch']}: "
            f"{s['trials']} trials ({states}), {s['minutes']:.0f} trial-minutes. Best trial {s['best_trial']}, "
            f"{s['monitor']} {s['best_value']:.4g} ({best}); trial 0, the config's own settings, {s['first_value']:.4g}. "
            f"Its trials: `{path.parent.name}/trials.md` beside the sweeps."
        )
    return lines


def table(out: Path) -> str:
    """One row per sweep, budget and batch, over its seeds; then each sweep's overrides and machine."""
    sweeps = {path.stem: results for path, results in results_in(out).items()}
    metric = next(k for k in next(iter(next(iter(sweeps.values())).values())) if k.startswith("model_")).removeprefix("model_")
    columns = ["sweep", "budget", "batch", "map / critic lr", "seeds", f"test {LABELS[metric]}, mean ± std", "per seed"]
    lines = header([*columns, "f_p alone"])
    for name, results in sweeps.items():
        for budget, batch in sorted({(r["budget"], r["batch"]) for r in results.values()}):
            group = sorted((r for r in results.values() if (r["budget"], r["batch"]) == (budget, batch)), key=lambda r: r["seed"])
            values = [r[f"model_{metric}"] for r in group]
            rates, f_p = f"{group[0]['map_lr']:.3g} / {group[0]['critic_lr']:.3g}", f"{group[0][f'fp_{metric}']:.4g}"
            lines.append(row([name, spaced(budget), batch, rates, len(group), mean_spread(values), listed(values), f_p]))
    lines.append("")
    for name, results in sweeps.items():
        first = next(iter(results.values()))
        machines = "; ".join(f"`{m}`" for m in dict.fromkeys(r["machine"] for r in results.values()))  # once each, in file order
        minutes = sum(r["fit_s"] for r in results.values()) / len(results) / 60
        settings = f", overrides `{' '.join(first['overrides'])}`" if first["overrides"] else ""
        lines.append(f"- `{name}`: {machines}{settings}; {minutes:.1f} min per fit on average.")
    lines += study_lines(out) + averaged_lines(out) + gap_lines(out)
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="fit and test every (budget, batch, seed)")
    run.add_argument("--out", default="results/budget")
    run.add_argument("--name", required=True, help="the sweep's name: its result file and run folder")
    run.add_argument("--config", required=True)
    run.add_argument("--budgets", type=int, nargs="+", required=True)
    how = run.add_mutually_exclusive_group(required=True)
    how.add_argument("--steps", type=int, help="training steps per run: batch = budget / steps")
    how.add_argument("--batches", type=int, nargs="+", help="fixed batch sizes")
    run.add_argument("--seeds", type=int, nargs="+", default=[0])
    run.add_argument("--metric", default="abs_err", help="the test metric recorded (abs_err; c2st for one-to-many tasks)")
    run.add_argument("overrides", nargs="*", help="after --: overrides for fit and test")
    record = commands.add_parser("study", help="record an otgb tune study's summary and files beside the sweeps")
    record.add_argument("--out", default="results/budget")
    record.add_argument("--name", required=True, help="the folder in --out for the study's files")
    record.add_argument("--storage", required=True, help="the study's sqlite:/// URL (its folder holds trials.md)")
    record.add_argument("--study", required=True)
    record.add_argument("--space", required=True, help="the space file the study searched, as the docs name it")
    join = commands.add_parser("merge", help="sweeps run side by side under their own names, as one sweep")
    join.add_argument("--out", default="results/budget")
    join.add_argument("--name", required=True, help="the merged sweep's name")
    join.add_argument("--parts", nargs="+", required=True, help="the names the parts ran under")
    mean = commands.add_parser("average", help="one grey-box with the mean of a sweep's seeds' f_phi, tested")
    mean.add_argument("--out", default="results/budget")
    mean.add_argument("--sweep", required=True, help="the sweep's name in --out")
    mean.add_argument("--folders", type=Path, nargs="+", required=True, help="its runs' folders, .../BUDGET/BATCH/seedN")
    where = commands.add_parser("gap", help="a sweep's seeds' maps against the true map: transport cost and distance")
    where.add_argument("--out", default="results/budget")
    where.add_argument("--sweep", required=True, help="the sweep's name in --out")
    where.add_argument("--folders", type=Path, nargs="+", required=True, help="its runs' folders, .../BUDGET/BATCH/seedN")
    where.add_argument("--inputs", type=int, default=4000, help="fresh inputs (and as many others for the distance)")
    show = commands.add_parser("table", help="the tables of every sweep in --out")
    show.add_argument("--out", default="results/budget")
    show.add_argument("--doc", help="a page to write the tables into, between the markers")
    args = parser.parse_args()
    if args.command == "run":
        sweep(args)
        return
    if args.command == "merge":
        merge(Path(args.out), args.name, args.parts)
        return
    if args.command == "average":
        average(Path(args.out), args.sweep, args.folders)
        return
    if args.command == "gap":
        gap(Path(args.out), args.sweep, args.folders, args.inputs)
        return
    if args.command == "study":
        record_study(Path(args.out) / args.name, args.storage, args.study, args.space)
        return
    text = table(Path(args.out))
    print(text)
    if args.doc:
        write_between(Path(args.doc), START, END, text)


if __name__ == "__main__":
    main()
