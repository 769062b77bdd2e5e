"""Does a 2-process DDP run learn as much as one process from the same simulations? Test ABS ERR over seeds.

    python scripts/ddp_seeds.py --config configs/advdiff.yaml --out bench/ddp --seeds 0 1 2 --steps 120

For each seed, three fits of ``--config`` on the same number of simulations (``--steps`` x the
config's batch), each followed by ``otgb test`` on its ``last.ckpt`` (the joint test set):

- ``1 process``: ``--steps`` steps of the config's batch;
- ``2 DDP, same batch per process``: half the steps, each of 2 x the batch (fewer, larger updates);
- ``2 DDP, same effective batch``: ``--steps`` steps of 2 x half the batch (the same updates' count and size).

``--variants single ddp-per-process ddp-effective`` picks some of them (default: all three).

Each run is a real 2-process gloo run through Lightning's launcher (``--trainer.strategy ddp
--trainer.devices 2 --trainer.accelerator cpu``). Prints a Markdown table of test ABS ERR per seed
with mean and std per row; finished runs (a test ``metrics.json``) are skipped when run again.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import yaml
from result_tables import header, row

from otgb.runs import fit_and_test

DDP = ["--trainer.strategy=ddp", "--trainer.devices=2", "--trainer.accelerator=cpu"]


VARIANTS = {
    "single": "1 process",
    "ddp-per-process": "2 DDP, same batch per process",
    "ddp-effective": "2 DDP, same effective batch",
}


def variants(batch: int, steps: int) -> dict[str, list[str]]:
    """The three runs on the same simulations: name -> fit overrides."""
    return {
        "1 process": [f"--trainer.max_steps={steps}"],
        "2 DDP, same batch per process": [*DDP, f"--trainer.max_steps={steps // 2}"],
        "2 DDP, same effective batch": [*DDP, f"--trainer.max_steps={steps}", f"--data.batch_size={batch // 2}"],
    }


def test_abs_err(out: Path, config: str, seed: int, name: str, overrides: list[str]) -> float:
    """Fit and test one variant on its last checkpoint (unless its test report exists); its test ABS ERR."""
    folder = out / f"seed{seed}" / name.replace(" ", "_").replace(",", "")
    steps = int(next(arg for arg in overrides if arg.startswith("--trainer.max_steps=")).split("=")[1])
    common = ["--config", config, f"--seed_everything={seed}", *overrides]
    common += ["--components.enabled=false", f"--trainer.val_check_interval={steps}"]
    return fit_and_test(folder, common, checkpoint="last")["model"]["abs_err"]["mean"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="a one-to-one config (ABS ERR needs one draw per input)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=120, help="steps of the 1-process run (even)")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS), help="which runs")
    args = parser.parse_args()
    if args.steps < 2 or args.steps % 2:
        raise SystemExit(f"--steps {args.steps}: expected an even number >= 2 (the 2-process run takes half)")
    if not Path(args.config).is_file():
        raise SystemExit(f"--config {args.config}: no such file")
    batch = yaml.safe_load(Path(args.config).read_text())["data"]["batch_size"]
    runs = {name: o for name, o in variants(batch, args.steps).items() if name in {VARIANTS[v] for v in args.variants}}
    rows = {name: [test_abs_err(args.out, args.config, seed, name, o) for seed in args.seeds] for name, o in runs.items()}
    print(f"{args.config}, {args.steps * batch} simulations per run; test ABS ERR\n")
    print("\n".join(header(["run", *(f"seed {s}" for s in args.seeds), "mean +- std"])))
    for name, values in rows.items():
        spread = f"{statistics.mean(values):.5f} +- {statistics.stdev(values):.5f}" if len(values) > 1 else "-"
        print(row([name, *(f"{v:.5f}" for v in values), spread]))


if __name__ == "__main__":
    main()
