"""Time the joint evaluation on a config's test set, and MMD's memory on 10^4 samples.

    python scripts/bench_evaluation.py --config configs/pendulum_mm.yaml [--repeats 5] [--ckpt best.ckpt]

Builds the test set as `otgb test` does and times :class:`otgb.metrics.joint.JointEvaluator`
with all metrics (ABS ERR/N-RMSE when M = 1, MMD, MMDAgg, C2ST) for (i) candidate draws that
come from the DGP itself (a near-chance C2ST), (ii) with ``--ckpt``, a trained model's draws
(the case `otgb test` meets), (iii) f_p alone, (iv) the Reference over ``--repeats`` splits.
Then MMD (both scalars) on 10^4 vs 10^4 samples of the same width, with the peak memory the
process added.
"""

from __future__ import annotations

import argparse
import resource
import time

import torch

from otgb.metrics import MMD, joint_samples
from otgb.metrics.joint import JointEvaluator, reference_scores
from otgb.runs import load_run, load_weights
from otgb.training import MapTraining


def timed(label: str, fn):
    start = time.perf_counter()
    out = fn()
    seconds = time.perf_counter() - start
    print(f"{label:<34} {seconds:7.1f} s   " + ", ".join(f"{k}={float(v):.4g}" for k, v in out.items() if not k.endswith("_std")))
    return out


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@torch.no_grad()
def model_draws(model: MapTraining, ckpt: str, data: dict[str, torch.Tensor]) -> torch.Tensor:
    """The checkpoint's draws (its moving average when it has one) for every test input, like `otgb test`."""
    load_weights(model, ckpt)
    draws = data["y"].shape[1]
    return model.generate(data["x"], data["x0"], data["theta"], draws)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True)
    parser.add_argument("--repeats", type=int, default=5, help="Reference splits")
    parser.add_argument("--mmd-samples", type=int, default=10_000)
    parser.add_argument("--ckpt", default=None, help="a checkpoint of the config's model: also time its draws")
    args = parser.parse_args()

    run = load_run(args.config)
    data_module = run.datamodule
    data_module.setup("test")
    data = data_module.test_set
    n, draws = data["y"].shape[:2]
    print(f"{args.config}: {n} test inputs x {draws} draws, threads {torch.get_num_threads()}")
    evaluator = JointEvaluator(tuple(data_module.physics.trajectory_shape))
    timed("model-like draws (DGP vs DGP)", lambda: evaluator.evaluate(data["y_ref"], data, tests=True))
    if args.ckpt is not None:
        y_hat = model_draws(run.model, args.ckpt, data)
        timed("trained model's draws", lambda: evaluator.evaluate(y_hat, data, tests=True))
    timed("f_p alone", lambda: evaluator.evaluate(data["x"].unsqueeze(1).expand_as(data["y"]), data, tests=True))
    timed(f"Reference ({args.repeats} splits)", lambda: reference_scores(evaluator, data, True, args.repeats))

    width = joint_samples(data["theta"], data["x0"], data["y"]).shape[1]
    g = torch.Generator().manual_seed(0)
    p, q = torch.randn(args.mmd_samples, width, generator=g), torch.randn(args.mmd_samples, width, generator=g)
    before = peak_rss_mb()
    metric = MMD()
    metric.update(p, q)
    timed(f"MMD {args.mmd_samples} vs {args.mmd_samples} (D={width})", metric.compute)
    full_matrix_mb = (2 * args.mmd_samples) ** 2 * 8 / 2**20
    print(f"peak memory added by MMD: {peak_rss_mb() - before:.0f} MB (a full float64 kernel matrix: {full_matrix_mb:.0f} MB)")


if __name__ == "__main__":
    main()
