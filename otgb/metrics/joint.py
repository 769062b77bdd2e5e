"""The joint evaluation of "Hybrid Generative Modeling for Incomplete Physics: Deep Grey-Box
Meets Optimal Transport" (ICLR 2025): one set of metrics for any generated draws y_hat
against the DGP's draws y on the same inputs (theta, x0).

- ABS ERR and N-RMSE pair y_hat_i with y_i (one-to-one sets, M = 1 draw per input);
- MMD (every evaluation) and, with ``tests``, the MMDAgg test and C2ST compare the joint
  samples (theta, x0, y_hat) and (theta, x0, y) (any M).

``reference_scores`` gives every metric's noise floor: the same metrics between two
independent DGP draw sets on the same inputs.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import MetricCollection

from otgb.metrics.c2st import C2ST
from otgb.metrics.errors import NRMSE, AbsErr
from otgb.metrics.mmd import MMD
from otgb.metrics.mmdagg import MMDAgg
from otgb.metrics.samples import joint_samples


class JointEvaluator:
    """Accumulates (y_hat, y, theta, x0) batches and computes the joint metrics.

    Args:
        trajectory_shape: (T, *obs) of one trajectory (tells the conv C2ST classifier where
            the trajectory starts in a joint sample row).
        c2st_folds: cross-validation folds of the C2ST.
        c2st_classifier: the C2ST classifier, "auto", "mlp", "conv" or a scikit-learn
            classifier (see :mod:`otgb.metrics.c2st`).
        c2st_precision: the C2ST classifier's arithmetic, "auto", "32-true" or "bf16-mixed".
        mmdagg_permutations: B1 = B2 of the MMDAgg test.
        seed: seed of the C2ST folds/classifier and of the MMDAgg permutations.
        device: where the accumulated states and the computations live.
        sync: gather the states of all processes when computing (False for data every
            process already holds whole, such as the f_p and Reference baselines).

    The two-sample metrics share one copy of the accumulated samples (a torchmetrics
    compute group), and everything syncs across processes when computed. Rows of the two
    joint samples are paired (same input and draw index), so MMDAgg permutes within pairs.
    """

    def __init__(
        self,
        trajectory_shape: tuple[int, ...],
        c2st_folds: int = 5,
        c2st_classifier: Any = "auto",
        c2st_precision: str = "auto",
        mmdagg_permutations: int = 500,
        seed: int = 0,
        device: torch.device | str = "cpu",
        sync: bool = True,
    ) -> None:
        kw = {"sync_on_compute": sync}
        self.errors = MetricCollection({"abs_err": AbsErr(**kw), "nrmse": NRMSE(**kw)}, compute_groups=False).to(device)
        self.two_sample = MetricCollection(
            {
                "mmd": MMD(**kw),
                "mmdagg": MMDAgg(n_permutations=mmdagg_permutations, n_level=mmdagg_permutations, seed=seed, paired=True, **kw),
                "c2st": C2ST(
                    folds=c2st_folds,
                    seed=seed,
                    classifier=c2st_classifier,
                    trajectory_shape=trajectory_shape,
                    precision=c2st_precision,
                    **kw,
                ),
            },
            compute_groups=True,
        ).to(device)
        self.device = torch.device(device)
        self.one_to_one: bool | None = None

    def update(self, y_hat: Tensor, y: Tensor, theta: Tensor, x0: Tensor) -> None:
        """Add a batch: y_hat and y (B, M, T, *obs) for the inputs theta (B, P), x0 (B, *state)."""
        if y_hat.shape != y.shape:
            raise ValueError(f"generated draws {tuple(y_hat.shape)} and DGP draws {tuple(y.shape)} differ in shape")
        move = lambda t: t.detach().to(self.device, torch.float32)  # noqa: E731
        y_hat, y, theta, x0 = map(move, (y_hat, y, theta, x0))
        self.one_to_one = y.shape[1] == 1
        if self.one_to_one:
            self.errors.update(y_hat[:, 0], y[:, 0])
        self.two_sample.update(joint_samples(theta, x0, y), joint_samples(theta, x0, y_hat))

    def compute(self, tests: bool) -> dict[str, Tensor]:
        """Named scalars: abs_err, nrmse (+ _std over inputs) when M = 1; mmd, mmd2_median;
        with ``tests`` also mmdagg_reject/_pvalue/_mmd2 and c2st (+ c2st_std over folds)."""
        if self.one_to_one is None:
            raise RuntimeError("JointEvaluator.compute called before any update")
        results: dict[str, Tensor] = {}
        if self.one_to_one:
            for metric in self.errors.values():
                results.update(metric.compute())
        for name in ("mmd", "mmdagg", "c2st") if tests else ("mmd",):
            # copy_state=False: the group's members read the shared samples instead of copying them
            results.update(self.two_sample.__getitem__(name, copy_state=False).compute())
        return {k: v.detach().float().cpu() for k, v in results.items()}

    def reset(self) -> None:
        self.errors.reset()
        self.two_sample.reset()
        self.one_to_one = None

    def evaluate(self, y_hat: Tensor, data: dict[str, Tensor], tests: bool, batch: int = 1024) -> dict[str, Tensor]:
        """All metrics of y_hat against ``data["y"]`` on a whole joint set, in one call."""
        self.reset()
        for start in range(0, len(y_hat), batch):
            s = slice(start, start + batch)
            self.update(y_hat[s], data["y"][s], data["theta"][s], data["x0"][s])
        results = self.compute(tests)
        self.reset()
        return results


def reference_scores(
    evaluator: JointEvaluator, data: dict[str, Tensor], tests: bool, repeats: int = 5, seed: int = 0
) -> dict[str, Tensor]:
    """The metrics between two independent DGP draw sets of the same size: the noise floor.

    ``data["y"]`` and ``data["y_ref"]`` hold M independent DGP draws each for the same inputs.
    Each repeat pools the 2M draws per input, splits them at random into two sets of M and
    scores one against the other; returns the mean over repeats (``<name>``) and the std
    (``<name>_std``).
    """
    if "y_ref" not in data:
        raise KeyError("reference scores need data['y_ref'], independent DGP draws for the same inputs")
    if repeats < 1:
        raise ValueError(f"reference_repeats={repeats}: expected >= 1")
    pooled = torch.cat([data["y"], data["y_ref"]], dim=1)
    n, draws = pooled.shape[:2]
    g = torch.Generator().manual_seed(seed)
    runs = []
    for _ in range(repeats):
        order = torch.rand(n, draws, generator=g).argsort(dim=1)
        shuffled = torch.gather(pooled, 1, order.reshape(n, draws, *([1] * (pooled.dim() - 2))).expand_as(pooled))
        half_a, half_b = shuffled[:, : draws // 2], shuffled[:, draws // 2 :]
        runs.append(evaluator.evaluate(half_a, {**data, "y": half_b}, tests))
    results = {}
    for name in runs[0]:
        if name.endswith("_std"):
            continue
        values = torch.stack([r[name] for r in runs])
        results[name] = values.mean()
        results[f"{name}_std"] = values.std() if repeats > 1 else torch.tensor(0.0)
    return results
