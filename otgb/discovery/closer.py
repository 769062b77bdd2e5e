"""Closer: is the augmented physics nearer to the test measurements than f_p alone, beyond chance?

The verification compares two models, the augmented physics A and f_p alone F, with one sample of
held-out measurements M. The statistic is the difference of their energy distances to M (Szekely &
Rizzo, "Energy statistics: A class of statistics based on distances"), ``E(A, M) - E(F, M)``, on
features standardised over the three samples together; below 0, A is nearer. Its p-value comes
from permutations of the model labels of the pooled A and F trajectories (M stays as it is): if
the named terms changed nothing the measurements can see, A and F are exchangeable and every
relabelling is as likely as the observed one. It is the permutation form of the question asked by
"A Test of Relative Similarity" (Bounliphone et al., 2016), one-sided: a small p-value says A is
closer to the measurements than F, not merely different from it. The terms measured on M alone
(``E(M, M)``) are the same for every labelling and cancel.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from otgb.discovery.locate import permutation_labels, z_scored


@dataclass
class Closeness:
    """The test's result: each model's energy distance to the measurements (on the common standardisation; ``draws``
    trajectories of each model), the one-sided permutation p-value of their difference, and whether it is below
    ``alpha``."""

    augmented: float
    f_p: float
    draws: int
    pvalue: float
    n_permutations: int
    alpha: float

    @property
    def difference(self) -> float:
        """E(augmented, measured) - E(f_p, measured): below 0, the augmented physics is nearer."""
        return self.augmented - self.f_p

    @property
    def significant(self) -> bool:
        return self.pvalue < self.alpha

    def to_dict(self) -> dict:
        return {**asdict(self), "difference": self.difference, "significant": self.significant}

    def clause(self) -> str:
        """The test in words, for the verdict."""
        if self.significant:
            return f"nearer to them than f_p alone by a permutation test, p = {self.pvalue:.2g}"
        return f"permutation test of which is nearer: p = {self.pvalue:.2g}"


def closer(augmented: Tensor, f_p: Tensor, measured: Tensor, n_permutations: int, alpha: float, seed: int) -> Closeness:
    """Whether ``augmented`` (n, ...) is nearer to ``measured`` (m, ...) than ``f_p`` (k, ...), by the energy distance."""
    n, k = len(augmented), len(f_p)
    if min(n, k, len(measured)) < 2:
        raise ValueError(f"closer: need at least 2 trajectories of each model and 2 measured; got {n}, {k}, {len(measured)}")
    models, measured = z_scored(torch.cat([augmented, f_p]).flatten(1).double(), measured.flatten(1).double())
    to_measured = torch.cdist(models, measured).mean(1)  # (n + k,): each model trajectory's mean distance to M
    within = torch.cdist(models, models)
    labels = permutation_labels(n, n + k, n_permutations, seed)  # (P + 1, n + k): 1 marks the augmented sample
    differences = _differences(labels, to_measured, within, n, k)
    pvalue = (1 + int((differences[1:] <= differences[0] + 1e-12).sum())) / (n_permutations + 1)
    m = len(measured)
    spread_m = float(torch.cdist(measured, measured).sum()) / (m * (m - 1))
    augmented_energy = float(2 * to_measured[:n].mean() - within[:n, :n].sum() / (n * (n - 1))) - spread_m
    f_p_energy = augmented_energy - float(differences[0])
    return Closeness(augmented_energy, f_p_energy, min(n, k), pvalue, n_permutations, alpha)


def _differences(labels: Tensor, to_measured: Tensor, within: Tensor, n: int, k: int) -> Tensor:
    """E(A, M) - E(F, M) for each labelling (rows of ``labels``), without the terms that depend on M alone."""
    others = 1 - labels
    cross = 2 * (labels @ to_measured / n - others @ to_measured / k)
    spread_a = torch.einsum("pi,ij,pj->p", labels, within, labels) / (n * (n - 1))
    spread_f = torch.einsum("pi,ij,pj->p", others, within, others) / (k * (k - 1))
    return cross - spread_a + spread_f
