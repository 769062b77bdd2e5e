"""Name: regress the learned correction f_phi on the candidate library, sparsely.

The idea of the universal differential equations ("Universal Differential Equations for
Scientific Machine Learning", Rackauckas et al. 2020) and of SINDy, applied to the OT grey-box:
f_phi is evaluated along generated trajectories and regressed on named candidate features.

- Columns are scaled to unit root mean square (so the constant stays a column like the others
  and variables on different scales weigh alike).
- The sparsity is chosen by cross-validation over the lasso path (scikit-learn's
  ``LassoLarsCV``), with folds that keep each trajectory's rows together (rows along one
  trajectory are strongly dependent), and the one-standard-error rule: the sparsest model
  whose held-out error is within one standard error of the best. The selected terms are then
  refitted by least squares (the lasso's coefficients are shrunk).
- A bootstrap over trajectories gives each candidate's inclusion probability and each selected
  coefficient's 95 % interval.
- A selected term is *ambiguous* with a candidate that can replace it without a held-out error
  worse by more than one standard error (``sin(angle)`` for ``angle`` at small angles), or with
  another selected term when either can be dropped (both selected, sharing one effect).
- The library's condition number and its confusable pairs (uncentred |correlation| >= 0.95)
  are reported; the evidence weighs each kept term against the terms it is paired with
  (:func:`otgb.discovery.evidence.moves_with`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from sklearn.exceptions import ConvergenceWarning
from sklearn.linear_model import LassoLars, LassoLarsCV, LinearRegression
from sklearn.model_selection import GroupKFold
from torch import Tensor

from otgb.discovery.library import Candidate
from otgb.discovery.seeds import SLOPE_BOOTSTRAP
from otgb.physics.base import PhysicsModel
from otgb.physics.features import evaluate_feature, parse_feature

MAX_ROWS = 60_000  # rows of the regression (cells of states along trajectories), subsampled beyond
FOLDS = 5
CONFUSABLE = 0.95  # |correlation| of a confusable pair: reported, and a kept term is weighed against each partner


@dataclass
class Design:
    """The library evaluated at states: X (rows, F) unscaled, y (rows,), the trajectory of each row."""

    candidates: list[Candidate]
    X: np.ndarray
    y: np.ndarray
    groups: np.ndarray
    scale: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.scale = np.sqrt((self.X**2).mean(0))

    @property
    def Xs(self) -> np.ndarray:
        return self.X / self.scale


@dataclass
class SelectedTerm:
    candidate: Candidate
    coefficient: float
    interval: tuple[float, float]
    inclusion_probability: float
    r2_share: float
    per_trajectory: dict[str, float]
    alternatives: list[Candidate]
    size: float  # RMS of the term's contribution to f_phi along the trajectories


@dataclass
class Selection:
    """The sparse regression of one component's correction."""

    component: str
    terms: list[SelectedTerm]
    explained_r2: float
    condition_number: float
    confusable_pairs: list[tuple[str, str, float]]
    inclusion: dict[str, float]
    target_rms: float


def design_matrix(
    model: PhysicsModel, candidates: list[Candidate], states: Tensor, theta: Tensor, target: Tensor, seed: int = 0,
    inputs: Tensor | None = None,
) -> Design:  # fmt: skip
    """Evaluate the candidates of one component at states (N, T, *state) with theta (N, P) and a driven model's input
    values along them (N, T, I).

    ``target`` (N, T, *grid) is the correction on that component. Rows are the (trajectory,
    time, cell) triples, subsampled at random to at most ``MAX_ROWS``.
    """
    n, steps = states.shape[:2]
    flat = states.flatten(0, 1).double()
    theta_rows = theta.double().repeat_interleave(steps, dim=0)
    powers = {}  # each factor (u^2, lap(v)) computed once for all candidates
    input_rows = None if inputs is None else inputs.double().flatten(0, 1)
    columns = [
        evaluate_feature(parse_feature(c.feature, model), flat, theta_rows, model, powers, input_rows).reshape(len(flat), -1)
        for c in candidates
    ]
    X = torch.stack(columns, dim=-1).reshape(-1, len(candidates))
    y = target.double().reshape(-1)
    cells = X.shape[0] // (n * steps)
    groups = torch.arange(n).repeat_interleave(steps * cells)
    keep = torch.isfinite(X).all(1) & torch.isfinite(y)
    index = keep.nonzero().squeeze(1)
    if len(index) > MAX_ROWS:
        g = torch.Generator().manual_seed(seed)
        index = index[torch.randperm(len(index), generator=g)[:MAX_ROWS]].sort().values
    return Design(candidates, X[index].numpy(), y[index].numpy(), groups[index].numpy())


def _usable(design: Design) -> np.ndarray:
    """Columns that are not zero everywhere (e.g. sign(v) when v never moves)."""
    return design.scale > 1e-12 * max(design.scale.max(), 1e-300)


def select_support(Xs: np.ndarray, y: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Indices of the columns chosen by grouped CV over the lasso path with the one-SE rule."""
    if not np.any(y):
        return np.array([], dtype=int)  # f_phi is exactly zero here: nothing to explain
    folds = min(FOLDS, len(np.unique(groups)))
    splits = list(GroupKFold(n_splits=folds).split(Xs, y, groups))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        cv = LassoLarsCV(fit_intercept=False, cv=splits, max_iter=200).fit(Xs, y)
        mse = cv.mse_path_.mean(1)
        se = cv.mse_path_.std(1) / np.sqrt(folds)
        best = int(np.argmin(mse))
        within = np.nonzero(mse <= mse[best] + se[best])[0]
        alpha = float(cv.cv_alphas_[within].max())  # the largest penalty: the sparsest model
        lasso = LassoLars(alpha=alpha, fit_intercept=False, max_iter=200).fit(Xs, y)
    return np.flatnonzero(np.abs(lasso.coef_) > 0)


def least_squares(X: np.ndarray, y: np.ndarray, support: np.ndarray) -> np.ndarray:
    coef = np.zeros(X.shape[1])
    if len(support):
        coef[support] = LinearRegression(fit_intercept=False).fit(X[:, support], y).coef_
    return coef


def r_squared(X: np.ndarray, y: np.ndarray, coef: np.ndarray) -> float:
    return float(1 - ((y - X @ coef) ** 2).sum() / max((y**2).sum(), 1e-300))


def fold_errors(Xs: np.ndarray, y: np.ndarray, groups: np.ndarray, support: np.ndarray) -> np.ndarray:
    """Held-out mean squared error per grouped fold of the least-squares fit on ``support``."""
    folds = min(FOLDS, len(np.unique(groups)))
    errors = []
    for train, test in GroupKFold(n_splits=folds).split(Xs, y, groups):
        coef = least_squares(Xs[train], y[train], support)
        errors.append(((y[test] - Xs[test] @ coef) ** 2).mean())
    return np.array(errors)


def regress(design: Design, component: str, n_bootstrap: int = 30, seed: int = 0) -> Selection:
    """Select the terms of one component's correction, with inclusion probabilities over a bootstrap."""
    usable = np.flatnonzero(_usable(design))
    Xs, y, groups = design.Xs[:, usable], design.y, design.groups
    support = select_support(Xs, y, groups)
    rng = np.random.default_rng(seed)
    trajectories = np.unique(groups)
    included = np.zeros(Xs.shape[1])
    for _ in range(n_bootstrap):
        rows = _resample(groups, trajectories, rng)
        included[select_support(Xs[rows], y[rows], groups[rows])] += 1
    inclusion = {design.candidates[usable[k]]: float(included[k] / n_bootstrap) for k in range(len(usable))}
    selected = [design.candidates[usable[j]] for j in support]
    correlation = Xs.T @ Xs / len(Xs)  # of unit-RMS columns: the uncentred correlation, as the regression sees them
    pairs = [
        (design.candidates[usable[a]].feature, design.candidates[usable[b]].feature, float(correlation[a, b]))
        for a in range(len(usable))
        for b in range(a + 1, len(usable))
        if abs(correlation[a, b]) >= CONFUSABLE
    ]
    return Selection(
        component=component,
        terms=describe_terms(design, selected, inclusion, n_bootstrap, seed),
        explained_r2=r_squared(Xs, y, least_squares(Xs, y, support)),
        condition_number=float(np.linalg.cond(Xs)),
        confusable_pairs=pairs,
        inclusion={c.feature: p for c, p in inclusion.items()},
        target_rms=float(np.sqrt((y**2).mean())),
    )


def describe_terms(
    design: Design, candidates: list[Candidate], inclusion: dict[Candidate, float], n_bootstrap: int = 30, seed: int = 0
) -> list[SelectedTerm]:
    """The least-squares fit of f_phi on ``candidates``: per term its coefficient, 95 % bootstrap interval
    (trajectories resampled), unique share of R^2, per-trajectory spread and ambiguous alternatives."""
    usable = np.flatnonzero(_usable(design))
    Xs, y, groups = design.Xs[:, usable], design.y, design.groups
    position = {design.candidates[i]: k for k, i in enumerate(usable)}
    support = np.array([position[c] for c in candidates], dtype=int)
    coef = least_squares(Xs, y, support)
    rng = np.random.default_rng(seed + SLOPE_BOOTSTRAP)
    trajectories = np.unique(groups)
    boot = np.array(
        [least_squares(Xs[rows], y[rows], support) for rows in (_resample(groups, trajectories, rng) for _ in range(n_bootstrap))]
    )
    r2 = r_squared(Xs, y, coef)
    base_errors = fold_errors(Xs, y, groups, support) if len(support) else None
    terms = []
    for j in support:
        scale = design.scale[usable[j]]
        low, high = np.percentile(boot[:, j], [2.5, 97.5]) / scale
        candidate = design.candidates[usable[j]]
        terms.append(
            SelectedTerm(
                candidate=candidate,
                coefficient=float(coef[j] / scale),
                interval=(float(low), float(high)),
                inclusion_probability=inclusion.get(candidate, 0.0),
                r2_share=r2 - r_squared(Xs, y, least_squares(Xs, y, support[support != j])),
                per_trajectory=_per_trajectory(Xs, y, groups, support, j, scale),
                alternatives=[design.candidates[usable[k]] for k in _alternatives(Xs, y, groups, support, j, base_errors)],
                size=float(abs(coef[j])),
            )
        )
    return terms


def _resample(groups: np.ndarray, trajectories: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Row indices of a bootstrap sample of whole trajectories."""
    rows_of = {g: np.flatnonzero(groups == g) for g in trajectories}
    return np.concatenate([rows_of[g] for g in rng.choice(trajectories, size=len(trajectories))])


def _as_good(Xs: np.ndarray, y: np.ndarray, groups: np.ndarray, support: np.ndarray, base_errors: np.ndarray) -> bool:
    """Whether the fit on ``support`` has a held-out error not worse than ``base_errors`` by more than one standard error."""
    difference = fold_errors(Xs, y, groups, support) - base_errors
    return bool(difference.mean() <= difference.std() / np.sqrt(len(difference)))


def _alternatives(
    Xs: np.ndarray, y: np.ndarray, groups: np.ndarray, support: np.ndarray, j: int, base_errors: np.ndarray
) -> list[int]:
    """Other explanations of column j's part of f_phi.

    If the fit without j is as good (j is redundant with other selected columns), those selected
    columns that are redundant too; otherwise the columns outside the selection that can replace
    j with a held-out error not worse by more than one standard error.
    """
    if _as_good(Xs, y, groups, support[support != j], base_errors):
        return [k for k in support if k != j and _as_good(Xs, y, groups, support[support != k], base_errors)]
    return [
        k
        for k in range(Xs.shape[1])
        if k not in support and _as_good(Xs, y, groups, np.append(support[support != j], k), base_errors)
    ]


def _per_trajectory(Xs: np.ndarray, y: np.ndarray, groups: np.ndarray, support: np.ndarray, j: int, scale: float) -> dict:
    """The coefficient of column j refitted on each trajectory alone: its spread across trajectories."""
    values = []
    for g in np.unique(groups):
        rows = groups == g
        if rows.sum() > len(support):
            values.append(least_squares(Xs[rows], y[rows], support)[j] / scale)
    values = np.array(values)
    q05, q50, q95 = np.percentile(values, [5, 50, 95])
    return {"mean": float(values.mean()), "std": float(values.std()), "q05": float(q05), "median": float(q50), "q95": float(q95)}


def subset_coefficients(design: Design, candidates: list[Candidate]) -> list[float]:
    """Least-squares coefficients (original units) of f_phi on ``candidates`` alone."""
    index = np.array([design.candidates.index(c) for c in candidates])
    return list(least_squares(design.Xs, design.y, index)[index] / design.scale[index])
