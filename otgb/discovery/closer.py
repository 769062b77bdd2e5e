"""Closer: is the augmented physics nearer to the test measurements than f_p alone, beyond chance?

The verification compares two models, the augmented physics A and f_p alone F, with one sample of
held-out measurements M. The statistic is the difference of their unbiased energy distances to M
(Szekely & Rizzo, "Energy statistics: A class of statistics based on distances"),
``D = E(A, M) - E(F, M)``, on features standardised over the three samples together; below 0, A is
nearer. The null hypothesis is that A is not nearer (``E[D] >= 0``), and two tests must both reject it:

- a permutation test: relabelling the pooled A and F trajectories (M fixed) is exact where the
  named terms changed nothing (A and F distributed alike), the case in which the normal
  approximation below is least reliable;
- the test of "A Test of Relative Similarity" (Bounliphone et al., 2016) for the energy distance:
  D over its standard error, from the first-order (Hoeffding) projections of D on each of the
  three samples. It counts M's own sampling noise, which the permutations keep fixed: where A and
  F differ but sit equally far from the process, a few test trajectories may lie nearer to one
  of them by chance, and only this test sees that.

The p-value is the larger of the two. A trajectory of the augmented physics that diverges counts
against it: its solve is no description of measurements that stayed finite, so it is not confirmed.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from otgb.data.gaps import with_gaps_of
from otgb.discovery.locate import permutation_labels, z_scored
from otgb.metrics.energy import batched_energy


@dataclass
class Closeness:
    """The test's result: each model's energy distance to the ``measured`` test trajectories and, on the same scale, the
    distance between two halves of them (``floor``); the trajectories of each model it used, those of the augmented
    physics that diverged, the two tests' p-values and the larger one, ``pvalue``."""

    augmented: float
    f_p: float
    floor: float
    measured: int
    augmented_draws: int
    f_p_draws: int
    diverged: int
    permutation_pvalue: float
    normal_pvalue: float
    n_permutations: int
    alpha: float

    @property
    def pvalue(self) -> float:
        return max(self.permutation_pvalue, self.normal_pvalue)

    @property
    def difference(self) -> float:
        """E(augmented, measured) - E(f_p, measured): below 0, the augmented physics is nearer."""
        return self.augmented - self.f_p

    @property
    def significant(self) -> bool:
        """Whether the augmented physics is nearer than f_p alone at level ``alpha``, none of its trajectories diverging."""
        return self.diverged == 0 and self.pvalue < self.alpha

    def to_dict(self) -> dict:
        return {**asdict(self), "pvalue": self.pvalue, "difference": self.difference, "significant": self.significant}

    def clause(self) -> str:
        """The test in words, for the verdict."""
        if self.diverged:
            return f"{self.diverged} of its {self.augmented_draws + self.diverged} trajectories diverged"
        smallest = 1 / (self.n_permutations + 1)
        said = f"p <= {smallest:.2g}" if self.pvalue <= smallest * (1 + 1e-9) else f"p = {self.pvalue:.2g}"
        return f"one-sided test, {said}" + ("" if self.significant else f", threshold {self.alpha:g}")


def closer(
    augmented: Tensor, f_p: Tensor, measured: Tensor, n_permutations: int, alpha: float, seed: int, diverged: int = 0
) -> Closeness:
    """Whether ``augmented`` (n, ...) is nearer to ``measured`` (m, ...) than ``f_p`` (k, ...), by the energy distance;
    rows of either model that are not finite are dropped and, for the augmented physics, added to ``diverged``. Where
    measured values are missing (NaN), both models take the measured gaps and every sample is 0 there
    (:mod:`otgb.data.gaps`): the permutations stay exact, the two models holding values at like places."""
    finite = [with_gaps_of(rows[rows.flatten(1).isfinite().all(1)], measured) for rows in (augmented, f_p)]
    diverged += len(augmented) - len(finite[0])
    (augmented, f_p), n, k, m = finite, len(finite[0]), len(finite[1]), len(measured)
    if min(n, k, m) < 4:
        raise ValueError(f"closer: need at least 4 finite trajectories of each model and 4 measured; got {n}, {k}, {m}")
    models, measured = z_scored(torch.cat([augmented, f_p]).flatten(1).double(), measured.flatten(1).double())
    energies = [float(energy(models[rows], measured)) for rows in (slice(0, n), slice(n, None))]
    to_measured, within = torch.cdist(models, measured), torch.cdist(models, models)
    del models
    labels = permutation_labels(n, n + k, n_permutations, seed)  # (P + 1, n + k): 1 marks the augmented sample
    differences = _differences(labels, to_measured.mean(1), within, n, k)
    tolerance = 1e-9 * float(differences.abs().max())
    permutation_p = (1 + int((differences[1:] <= differences[0] + tolerance).sum())) / (n_permutations + 1)
    normal_p = _normal_pvalue(to_measured, within, n, k, m, float(differences[0]))
    order = torch.randperm(m, generator=torch.Generator().manual_seed(seed))  # the floor: one half against the other
    floor = float(energy(measured[order[: m // 2]], measured[order[m // 2 : 2 * (m // 2)]]))
    return Closeness(*energies, floor, m, n, k, diverged, permutation_p, normal_p, n_permutations, alpha)


def energy(a: Tensor, b: Tensor) -> Tensor:
    """The unbiased energy distance between the rows of ``a`` and ``b``, as they are (no standardising)."""
    return batched_energy(a[None], b[None])[0]


def _differences(labels: Tensor, to_measured: Tensor, within: Tensor, n: int, k: int) -> Tensor:
    """E(A, M) - E(F, M) for each labelling (rows of ``labels``), without the terms that depend on M alone."""
    others = 1 - labels
    cross = 2 * (labels @ to_measured / n - others @ to_measured / k)
    spread_a = torch.einsum("pi,ij,pj->p", labels, within, labels) / (n * (n - 1))
    spread_f = torch.einsum("pi,ij,pj->p", others, within, others) / (k * (k - 1))
    return cross - spread_a + spread_f


def _normal_pvalue(to_measured: Tensor, within: Tensor, n: int, k: int, m: int, difference: float) -> float:
    """P(Z <= D / se) with se from D's first-order projections on A, F and M (each a mean over one sample's rows)."""
    a, f = slice(0, n), slice(n, None)
    on_m = 2 * (to_measured[a].mean(0) - to_measured[f].mean(0))  # (m,)
    on_a = 2 * (to_measured[a].mean(1) - within[a, a].sum(1) / (n - 1))  # (n,)
    on_f = -2 * (to_measured[f].mean(1) - within[f, f].sum(1) / (k - 1))  # (k,)
    variance = float(on_m.var() / m + on_a.var() / n + on_f.var() / k)
    if not variance > 0:  # every row alike: D is exact
        return 0.0 if difference < 0 else 1.0
    return 0.5 * math.erfc(-difference / math.sqrt(variance) / math.sqrt(2))
