"""Measured rod temperatures from an independent solver (SciPy's ``solve_ivp`` on the method of lines), with a decay
that otgb is not told.

The rod of ``configs/advdiff.yaml`` (20 points s = 0.1, ..., 2.0 between zero Dirichlet ends at s = 0 and 2.1,
alpha ~ U(0.01, 0.1), released from c sin(pi s / 2) with c ~ U(0.5, 1.5), the field observed at t = 0, 0.02, ...,
0.98 with white noise), plus a decay -k T on dT/dt whose rate k each trajectory draws from U(k - spread, k + spread)::

    python scripts/scipy_advdiff.py --k 0.6 --spread 0.3 --n 1000 --seed 0 --out decay.npz

The file holds ``y`` (n, 50, 1, 20) only (theta and x0 not recorded).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

GRID = 20
DX = 0.1
TIMES = np.arange(50) * 0.02
SOLVER = {"rtol": 1e-9, "atol": 1e-11, "method": "DOP853"}


def laplacian(field: np.ndarray) -> np.ndarray:
    """Second-order central differences with zero values beyond both ends."""
    padded = np.concatenate([[0.0], field, [0.0]])
    return (padded[2:] - 2 * padded[1:-1] + padded[:-2]) / DX**2


def _field(_, T: np.ndarray, alpha: float, rate: float) -> np.ndarray:
    return alpha * laplacian(T) - rate * T


def write(path: Path, k: float, spread: float, n: int, seed: int, noise: float) -> Path:
    """``n`` rods with a decay rate drawn per trajectory from U(k - ``spread``, k + ``spread``), to the ``.npz`` ``path``."""
    rng = np.random.default_rng(seed)
    s = DX * np.arange(1, GRID + 1)
    y = np.empty((n, len(TIMES), 1, GRID), dtype=np.float32)
    for i in range(n):
        alpha, amplitude = rng.uniform(0.01, 0.1), rng.uniform(0.5, 1.5)
        rate = k if spread == 0 else rng.uniform(k - spread, k + spread)
        start = amplitude * np.sin(np.pi * s / 2)
        solved = solve_ivp(_field, (0, TIMES[-1]), start, t_eval=TIMES, args=(alpha, rate), **SOLVER)
        y[i, :, 0] = solved.y.T + rng.normal(0, noise, (len(TIMES), GRID))
    np.savez(path, y=y)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--k", type=float, default=0.6, help="the decay rate's centre (dT/dt gains -k T)")
    parser.add_argument("--spread", type=float, default=0.0, help="k drawn per trajectory from U(k - spread, k + spread)")
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    write(args.out, args.k, args.spread, args.n, args.seed, args.noise)


if __name__ == "__main__":
    main()
