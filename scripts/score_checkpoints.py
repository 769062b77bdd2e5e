"""Score every checkpoint of a run on a config's joint validation and test sets (a script that knows the DGP).

    python scripts/score_checkpoints.py --config configs/pendulum.yaml --run runs/pendulum/version_0

For a run trained in the measured-data mode (keep every checkpoint: ``--checkpoint.save_top_k -1``),
this says which checkpoint each validation metric of the run selects (its own ``metrics.csv``:
``val/energy``, ``val/mmd``, ...) and which one the joint validation ABS ERR would have selected,
and the joint test ABS ERR of each: how much the marginal selection loses against knowing the DGP,
within one training run. Writes ``<run>/checkpoint_scores.md``.
"""

from __future__ import annotations

import argparse
import csv
import re
from pathlib import Path

import torch

from otgb.metrics import abs_err
from otgb.runs import load_run, load_weights
from otgb.training import MapTraining

CRITERIA = ("val/energy", "val/mmd", "val/mmd2_median")


@torch.no_grad()
def joint_abs_err(model: MapTraining, data: dict[str, torch.Tensor]) -> float:
    y_hat = model.generate(data["x"], data["x0"], data["theta"], 1)
    return float(abs_err(y_hat[:, 0], data["y"][:, 0]).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="a config whose data.hidden_effect is the DGP of the run's measurements")
    parser.add_argument("--run", type=Path, required=True, help="the run's version directory (metrics.csv, checkpoints/)")
    args, overrides = parser.parse_known_args()
    run = load_run(args.config, *overrides)
    model, data = run.model, run.datamodule
    data.setup("validate")
    data.setup("test")
    scores = {}
    step_of = lambda path: int(re.search(r"step=(\d+)", path.name).group(1))  # noqa: E731
    for path in sorted((args.run / "checkpoints").glob("*step=*.ckpt"), key=step_of):
        step = step_of(path)
        load_weights(model, path)
        model.eval()
        scores[step] = {"val": joint_abs_err(model, data.val_set), "test": joint_abs_err(model, data.test_set)}
    with open(args.run / "metrics.csv") as handle:
        rows = list(csv.DictReader(handle))
    logged = {c: {int(float(r["step"])) + 1: float(r[c]) for r in rows if r.get(c)} for c in CRITERIA}
    lines = ["| selected by | step | joint test ABS ERR |", "|---|---|---|"]
    choices = {"joint val ABS ERR (knows the DGP)": min(scores, key=lambda s: scores[s]["val"])}
    choices.update({c: min((s for s in logged[c] if s in scores), key=logged[c].get) for c in CRITERIA if logged[c]})
    choices["last"] = max(scores)
    for criterion, step in choices.items():
        lines.append(f"| {criterion} | {step} | {scores[step]['test']:.4g} |")
    lines += [
        "",
        "| step | joint val ABS ERR | joint test ABS ERR | " + " | ".join(CRITERIA) + " |",
        "|---" * (3 + len(CRITERIA)) + "|",
    ]
    for step, score in scores.items():
        marginal = " | ".join(f"{logged[c][step]:.4g}" if step in logged[c] else "" for c in CRITERIA)
        lines.append(f"| {step} | {score['val']:.4g} | {score['test']:.4g} | {marginal} |")
    (args.run / "checkpoint_scores.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
