"""Classifier two-sample test (Lopez-Paz & Oquab 2017, "Revisiting Classifier Two-Sample Tests") on joint samples.

Label the rows of p with 0 and of q with 1, z-score all rows with the mean and std of p
(the reference sample), and report the k-fold cross-validated accuracy of a classifier
(stratified, shuffled with ``seed``): about 0.5 when p and q are indistinguishable, 1 when
they are fully separable. Under the null the accuracy over N held-out predictions is about
N(1/2, 1/(4N)), so 3 standard errors are 1.5 / sqrt(N).

Joint samples of model and DGP share their inputs: the rows for one (theta, x0) appear in
both classes. Split naively, a held-out row would have a near twin of the other class in
the training folds, and a flexible classifier scores *below* 0.5 even when p = q. With
``trajectory_shape`` given, rows are therefore grouped by their conditioning inputs (the
features before the trajectory) and the folds keep each group together
(StratifiedGroupKFold); with fewer distinct inputs than folds, the folds are plain stratified.

Classifiers (``classifier``):
- ``"mlp"``: sbi's ``c2st`` MLP (hidden layers (10 d, 10 d), ReLU, Adam) with early stopping
  on 10 % of the training fold (10 epochs without improvement); for low-dimensional joint
  samples such as the pendulum's (d = 53). It is :class:`otgb.metrics.classifiers.MLPClassifier`,
  scikit-learn's MLPClassifier algorithm in torch: 1.7x faster on a CPU in float32, about 3x
  in bfloat16 mixed precision where the CPU has it (``precision``), and it trains on the
  samples' device.
- ``"conv"``: :class:`otgb.metrics.classifiers.ConvClassifier`, a small convolutional net over
  the trajectory part of each row, for PDE observations (d in the thousands).
- ``"paper"``: :class:`otgb.metrics.classifiers.PaperConvClassifier`, the paper's judge network
  (three 3-filter convolutions along the whole row): a weak judge, to place a figure on the
  scale of the paper's Table 1, next to a strong judge's.
- ``"auto"`` (default): "mlp" up to ``AUTO_MLP_MAX_FEATURES`` features, "conv" above.
- or any scikit-learn classifier (it is cloned per fold).

On a CPU the folds train at once, in threads, each on its share of torch's threads: the judges'
networks are too small for torch to spread one over several cores (``scripts/speed_benchmark.py
judges`` measures the gain). Each fold's network starts from ``seed`` as before, so the folds in
threads give what they give one after the other, up to float rounding.

``n_permutations`` > 0 adds a permutation p-value: the same cross-validation on randomly
relabelled rows, p = (1 + #{acc_perm >= acc}) / (n_permutations + 1).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import partial
from typing import Any

import joblib
import numpy as np
import torch
from sklearn.base import clone
from sklearn.model_selection import StratifiedGroupKFold, StratifiedKFold, cross_val_score
from torch import Tensor

from otgb.metrics.classifiers import ConvClassifier, MLPClassifier, PaperConvClassifier
from otgb.metrics.samples import TwoSampleMetric

AUTO_MLP_MAX_FEATURES = 200  # an MLP of width 10 d is slow on a CPU well before d = 1000
CLASSIFIERS = ("auto", "mlp", "conv", "paper")


def c2st(
    p: Tensor,
    q: Tensor,
    folds: int = 5,
    seed: int = 0,
    classifier: Any = "auto",
    trajectory_shape: tuple[int, ...] | None = None,
    n_permutations: int = 0,
    precision: str = "auto",
    n_jobs: int | None = None,
) -> dict[str, Tensor]:
    """Cross-validated accuracy of telling p (n, D) from q (m, D) apart.

    ``trajectory_shape`` (T, *obs) says which trailing features form the trajectory (the
    leading ones are the conditioning inputs theta, x0): the folds group rows by their inputs,
    and the "conv" classifier reads the trajectory.
    ``precision`` ("auto", "32-true", "bf16-mixed") is the "mlp"/"conv" classifier's
    arithmetic (see :mod:`otgb.metrics.classifiers`).
    ``n_jobs``: folds trained at once on a CPU (None: as many as torch has threads, at most ``folds``).
    Returns ``c2st`` (mean accuracy over folds), ``c2st_std`` (std over folds) and, with
    permutations, ``c2st_pvalue``.
    """
    if p.dim() != 2 or q.dim() != 2 or p.shape[1] != q.shape[1]:
        raise ValueError(f"c2st: expected (n, D) and (m, D), got {tuple(p.shape)} and {tuple(q.shape)}")
    if folds < 2 or min(len(p), len(q)) < folds:
        raise ValueError(f"c2st: {folds}-fold cross-validation needs folds >= 2 and >= {folds} rows per sample")
    if n_jobs is not None and n_jobs < 1:
        raise ValueError(f"c2st: n_jobs={n_jobs}, expected None (as many folds at once as torch has threads) or >= 1")
    estimator = make_classifier(classifier, p.shape[1], trajectory_shape, seed, str(p.device), precision)
    mean, std = p.double().mean(0), p.double().std(0)
    std = torch.where(std > 0, std, torch.ones_like(std))
    features = ((torch.cat([p, q]).double() - mean) / std).float().cpu().numpy()
    labels = np.r_[np.zeros(len(p)), np.ones(len(q))].astype(np.int64)
    groups = input_groups(torch.cat([p, q]), trajectory_shape)
    if groups is not None and len(np.unique(groups)) < folds:
        groups = None  # too few distinct inputs (e.g. an experiment run at 3 settings) to keep them apart in folds
    if groups is None:
        cv = StratifiedKFold(n_splits=folds, shuffle=True, random_state=seed)
    else:
        cv = StratifiedGroupKFold(n_splits=folds, shuffle=True, random_state=seed)
    with folds_in_threads(folds if p.device.type == "cpu" else 1, n_jobs) as jobs:
        cross_validate = partial(cross_val_score, estimator, features, groups=groups, cv=cv, error_score="raise", n_jobs=jobs)
        scores = cross_validate(labels, scoring="accuracy")
        result = {"c2st": torch.tensor(scores.mean()).float(), "c2st_std": torch.tensor(scores.std()).float()}
        if n_permutations > 0:
            rng = np.random.default_rng(seed)
            null = [cross_validate(rng.permutation(labels)).mean() for _ in range(n_permutations)]
            result["c2st_pvalue"] = torch.tensor((1 + sum(a >= scores.mean() for a in null)) / (n_permutations + 1)).float()
    return result


@contextmanager
def folds_in_threads(folds: int, n_jobs: int | None) -> Iterator[int]:
    """Joblib's thread backend for ``n_jobs`` folds at once (None: torch's thread count, at most ``folds``), with
    torch's threads shared out among them for the duration; yields the number of folds trained at once."""
    threads = torch.get_num_threads()
    jobs = min(folds, threads if n_jobs is None else n_jobs)
    if jobs == 1:
        yield 1
        return
    torch.set_num_threads(max(1, threads // jobs))
    try:
        with joblib.parallel_config(backend="threading"):
            yield jobs
    finally:
        torch.set_num_threads(threads)


def input_groups(rows: Tensor, trajectory_shape: tuple[int, ...] | None) -> np.ndarray | None:
    """Group id per row: rows with equal conditioning features (those before the trajectory) share one."""
    if trajectory_shape is None:
        return None
    cond_dim = rows.shape[1] - int(np.prod(trajectory_shape))
    if cond_dim <= 0:
        return None
    return torch.unique(rows[:, :cond_dim], dim=0, return_inverse=True)[1].cpu().numpy()


def make_classifier(
    classifier: Any,
    n_features: int,
    trajectory_shape: tuple[int, ...] | None,
    seed: int,
    device: str = "cpu",
    precision: str = "auto",
) -> Any:
    """The estimator behind a ``classifier`` setting (see the module docstring); "mlp" and "conv" train on
    ``device`` in ``precision``."""
    if not isinstance(classifier, str):
        return clone(classifier)
    if classifier not in CLASSIFIERS:
        raise ValueError(f"c2st: classifier={classifier!r}, expected one of {CLASSIFIERS} or a scikit-learn classifier")
    if classifier == "auto":
        classifier = "mlp" if n_features <= AUTO_MLP_MAX_FEATURES else "conv"
    if classifier == "paper":
        return PaperConvClassifier(random_state=seed, device=device, precision=precision)
    if classifier == "mlp":
        width = 10 * n_features
        return MLPClassifier(hidden=(width, width), random_state=seed, device=device, precision=precision)
    if trajectory_shape is None:
        raise ValueError("c2st: the 'conv' classifier needs trajectory_shape (T, *obs) to find the trajectory in each row")
    n_traj = int(np.prod(trajectory_shape))
    if n_traj > n_features:
        raise ValueError(f"c2st: trajectory_shape {tuple(trajectory_shape)} has more features than the rows ({n_features})")
    return ConvClassifier(
        trajectory_shape=tuple(trajectory_shape),
        cond_dim=n_features - n_traj,
        random_state=seed,
        device=device,
        precision=precision,
    )


class C2ST(TwoSampleMetric):
    """C2ST accuracy on accumulated samples: ``{"c2st", "c2st_std"[, "c2st_pvalue"]}``.

    Args:
        folds: number of cross-validation folds.
        seed: seed of the folds and of the classifier.
        classifier: "auto", "mlp", "conv" or a scikit-learn classifier (see the module docstring).
        trajectory_shape: (T, *obs) of the trajectory part of each row (None: no grouping by inputs).
        n_permutations: relabelled cross-validations for a permutation p-value (0: none).
        precision: the "mlp"/"conv" classifier's arithmetic, "auto", "32-true" or "bf16-mixed".
        **kwargs: torchmetrics Metric options (e.g. ``sync_on_compute``).
    """

    def __init__(
        self,
        folds: int = 5,
        seed: int = 0,
        classifier: Any = "auto",
        trajectory_shape: tuple[int, ...] | None = None,
        n_permutations: int = 0,
        precision: str = "auto",
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.options = dict(
            folds=folds,
            seed=seed,
            classifier=classifier,
            trajectory_shape=trajectory_shape,
            n_permutations=n_permutations,
            precision=precision,
        )

    def score(self, p: Tensor, q: Tensor) -> dict[str, Tensor]:
        return c2st(p, q, **self.options)
