"""One set of metrics for generated draws y_hat against measured draws y.

Joint (the evaluation of "Hybrid Generative Modeling for Incomplete Physics: Deep Grey-Box
Meets Optimal Transport", section "Evaluation"): rows (theta, x0, y) with the DGP's draws for
the same inputs as the map's. Marginal: rows y alone, the map's draws for inputs from the
priors against held-out measurements.

- ABS ERR and N-RMSE pair y_hat_i with y_i (joint one-to-one sets, M = 1 draw per input);
- MMD and the energy distance (every evaluation) and, with ``tests``, the MMDAgg test and
  C2ST compare the two samples of rows (any M).

Noise floors (the Reference): ``reference_scores`` compares two independent DGP draw sets on
the same inputs (joint); ``split_half_scores`` two random halves of the measurements (marginal).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import MetricCollection

from otgb.data.gaps import has_gaps
from otgb.metrics.c2st import C2ST
from otgb.metrics.energy import EnergyDistance
from otgb.metrics.errors import NRMSE, AbsErr
from otgb.metrics.mmd import MMD
from otgb.metrics.mmdagg import MMDAgg
from otgb.metrics.samples import mean_and_std, random_halves, sample_rows


class JointEvaluator:
    """Accumulates (y_hat, y, inputs) batches and computes the metrics on rows (inputs, trajectory).

    Args:
        trajectory_shape: (T, *obs) of one trajectory (tells the conv C2ST classifier and the
            per-time statistic where the trajectory starts in a sample row).
        inputs: the batch entries that condition each row, ("theta", "x0") for the joint
            evaluation; () compares the trajectories' marginal distributions alone.
        paired: whether row i of y_hat and row i of y share their inputs (the map evaluated on
            the inputs of the measured draw); MMDAgg then permutes within pairs. ABS ERR and
            N-RMSE are computed when the pairs are fully determined (inputs cover theta and x0)
            and there is one draw per input.
        per_time: also compute the energy distance per time step and component (``energy_per_time``).
        c2st_folds: cross-validation folds of the C2ST.
        c2st_classifier: the C2ST classifier, "auto", "mlp", "conv" or a scikit-learn
            classifier (see :mod:`otgb.metrics.c2st`).
        c2st_precision: the C2ST classifier's arithmetic, "auto", "32-true" or "bf16-mixed".
        mmdagg_permutations: B1 = B2 of the MMDAgg test.
        seed: seed of the C2ST folds/classifier and of the MMDAgg permutations.
        device: where the accumulated states and the computations live.
        sync: gather the states of all processes when computing (False for data every
            process already holds whole, such as the f_p and Reference baselines).
        across_halves: for unpaired draws made on the very inputs of the measured rows (one measured row
            per input), score one random half of the inputs' measured rows against the draws of the
            other half, mean and ``_std`` over this many splits (:func:`otgb.metrics.samples.random_halves` with
            ``seed``), so that no draw is compared with its own measurement; 0: the whole samples.

    The two-sample metrics share one copy of the accumulated samples (a torchmetrics
    compute group), and everything syncs across processes when computed.
    """

    def __init__(
        self,
        trajectory_shape: tuple[int, ...],
        inputs: tuple[str, ...] = ("theta", "x0"),
        paired: bool = True,
        per_time: bool = True,
        c2st_folds: int = 5,
        c2st_classifier: Any = "auto",
        c2st_precision: str = "auto",
        mmdagg_permutations: int = 500,
        seed: int = 0,
        device: torch.device | str = "cpu",
        sync: bool = True,
        across_halves: int = 0,
    ) -> None:
        kw = {"sync_on_compute": sync}
        self.inputs, self.paired = tuple(inputs), paired
        if across_halves and paired:
            raise ValueError("across_halves compares different inputs: the evaluator must be unpaired")
        self.pointwise = self.is_pointwise(self.inputs, paired)
        self.errors = MetricCollection({"abs_err": AbsErr(**kw), "nrmse": NRMSE(**kw)}, compute_groups=False).to(device)
        self.two_sample = MetricCollection(
            {
                "mmd": MMD(**kw),
                "energy": EnergyDistance(trajectory_shape=trajectory_shape if per_time else None, paired=paired, **kw),
                "mmdagg": MMDAgg(n_permutations=mmdagg_permutations, n_level=mmdagg_permutations, seed=seed, paired=paired, **kw),
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
        for metric in self.two_sample.values():
            metric.across_halves = (across_halves, seed)
        self.device = torch.device(device)
        self.one_to_one: bool | None = None

    @staticmethod
    def is_pointwise(inputs: tuple[str, ...], paired: bool) -> bool:
        """ABS ERR and N-RMSE need pairs whose inputs determine the trajectory: theta and x0 both."""
        return paired and set(inputs) == {"theta", "x0"}

    def update(
        self, y_hat: Tensor, batch: dict[str, Tensor], candidate: dict[str, Tensor] | None = None,
        as_measured: Tensor | None = None,
    ) -> None:  # fmt: skip
        """Add draws y_hat (B, M, T, *obs) against ``batch["y"]`` (B', M', T, *obs).

        The rows of ``batch["y"]`` are conditioned on the batch's inputs, those of y_hat on
        ``candidate``'s (default: the same batch, which a paired evaluation needs). ``as_measured``:
        the draws as the two-sample metrics see them (with the measurements' noise; default y_hat);
        the pointwise errors take y_hat itself, the best guess of a noisy measurement.
        """
        y = batch["y"]
        if self.paired and (candidate is not None or y_hat.shape != y.shape):
            raise ValueError(f"paired draws need the same inputs and shape: got {tuple(y_hat.shape)} and {tuple(y.shape)}")
        move = lambda t: t.detach().to(self.device, torch.float32)  # noqa: E731
        y_hat, y = move(y_hat), move(y)
        self.one_to_one = y.shape[1] == 1
        if self.pointwise and self.one_to_one:
            self.errors.update(y_hat[:, 0], y[:, 0])
        cond = self._conditioning(batch)
        cond_hat = cond if candidate is None else self._conditioning(candidate)
        compared = y_hat if as_measured is None else move(as_measured)
        compared, y = comparable_draws(compared, y)
        self.two_sample.update(sample_rows(move(cond), y), sample_rows(move(cond_hat), compared))

    def _conditioning(self, batch: dict[str, Tensor]) -> Tensor:
        parts = [batch[name].flatten(1) for name in self.inputs]
        return torch.cat(parts, dim=1) if parts else batch["y"].new_zeros(len(batch["y"]), 0)

    def compute(self, tests: bool) -> dict[str, Tensor]:
        """Named results: abs_err, nrmse (+ _std over inputs) when pointwise; mmd, mmd2_median, energy and
        energy_per_time (T, C); with ``tests`` also mmdagg_reject/_pvalue/_mmd2 and c2st (+ c2st_std over folds)."""
        if self.one_to_one is None:
            raise RuntimeError("JointEvaluator.compute called before any update")
        results: dict[str, Tensor] = {}
        if self.pointwise and self.one_to_one:
            for metric in self.errors.values():
                results.update(metric.compute())
        for name in ("mmd", "energy", "mmdagg", "c2st") if tests else ("mmd", "energy"):
            # copy_state=False: the group's members read the shared samples instead of copying them
            results.update(self.two_sample.__getitem__(name, copy_state=False).compute())
        return {k: v.detach().float().cpu() for k, v in results.items()}

    def reset(self) -> None:
        self.errors.reset()
        self.two_sample.reset()
        self.one_to_one = None

    def evaluate(
        self, y_hat: Tensor, data: dict[str, Tensor], tests: bool, candidate: dict[str, Tensor] | None = None,
        as_measured: Tensor | None = None,
    ) -> dict[str, Tensor]:  # fmt: skip
        """All metrics of y_hat (inputs: ``candidate``, default ``data``) against ``data["y"]``, in one call."""
        self.reset()
        self.update(y_hat, data, candidate, as_measured)
        results = self.compute(tests)
        self.reset()
        return results


def reference_scores(
    evaluator: JointEvaluator, data: dict[str, Tensor], tests: bool, repeats: int = 5, seed: int = 0
) -> dict[str, Tensor]:
    """The metrics between two independent DGP draw sets of the same size: the joint noise floor.

    ``data["y"]`` and ``data["y_ref"]`` hold M independent DGP draws each for the same inputs.
    Each repeat pools the 2M draws per input, splits them at random into two sets of M and
    scores one against the other; returns the mean over repeats (``<name>``) and the std
    (``<name>_std``).
    """
    if "y_ref" not in data:
        raise KeyError("reference scores need data['y_ref'], independent DGP draws for the same inputs")
    _check_repeats(repeats)
    pooled = torch.cat([data["y"], data["y_ref"]], dim=1)
    n, draws = pooled.shape[:2]
    g = torch.Generator().manual_seed(seed)
    runs = []
    for _ in range(repeats):
        order = torch.rand(n, draws, generator=g).argsort(dim=1)
        shuffled = torch.gather(pooled, 1, order.reshape(n, draws, *([1] * (pooled.dim() - 2))).expand_as(pooled))
        half_a, half_b = shuffled[:, : draws // 2], shuffled[:, draws // 2 :]
        runs.append(evaluator.evaluate(half_a, {**data, "y": half_b}, tests))
    return mean_and_std(runs)


def split_half_scores(
    evaluator: JointEvaluator, data: dict[str, Tensor], tests: bool, repeats: int = 5, seed: int = 0
) -> dict[str, Tensor]:
    """The metrics between two random halves of a set of measurements: the marginal noise floor.

    Each repeat splits the rows of ``data`` (y with its inputs) at random into two halves and
    scores one against the other with an unpaired ``evaluator``; mean and ``_std`` over repeats.
    The halves are half the size of the set: the unbiased statistics (``mmd2_median``,
    ``energy``) keep their mean and double their spread; the biased paper-code ``mmd`` (a
    V-statistic) sits about twice as high as a comparison of the whole set with equally many
    draws would for equal distributions.
    """
    if evaluator.paired:
        raise ValueError("split-half scores compare different inputs: the evaluator must be unpaired")
    _check_repeats(repeats)
    runs = []
    for first, second in random_halves(len(data["y"]), repeats, seed):
        half_a, half_b = ({k: v[idx] for k, v in data.items()} for idx in (first, second))
        runs.append(evaluator.evaluate(half_b["y"], half_a, tests, candidate=half_b))
    return mean_and_std(runs)


def _check_repeats(repeats: int) -> None:
    if repeats < 1:
        raise ValueError(f"reference_repeats={repeats}: expected >= 1")


def comparable_draws(draws: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """Draws (B, M, T, *obs) and measurements y (B, M', T, *obs) as the two-sample metrics compare them: row b of both
    missing (NaN) wherever either misses a value (y's gaps, and the draws' own where they are measured, as a
    Reference's half is), so that both samples hold values at like places (:mod:`otgb.data.gaps`)."""
    if not (has_gaps(y) or has_gaps(draws)):
        return draws, y
    missing = torch.isnan(y).any(dim=1, keepdim=True) | torch.isnan(draws).any(dim=1, keepdim=True)
    return draws.masked_fill(missing, float("nan")), y.masked_fill(missing, float("nan"))
