"""Measured pendulum files from an independent solver (SciPy's ``solve_ivp``, DOP853), with a friction law of choice.

The pendulum of ``configs/pendulum.yaml`` (omega ~ U(0.785, 3.14) rad/s, released at rest from an angle ~ U(-1.57,
1.57) rad, the angle observed at t = 0, 0.1, ..., 4.9 s with white noise), plus a friction on d velocity/dt that
otgb is not told: the file holds ``trajectory``, ``t`` and ``angle`` only (theta and x0 not recorded)::

    python scripts/scipy_pendulum.py --law rational --c 0.8 --v0 2.0 --n 1000 --seed 0 --out rational.csv

A restoring force weaker than f_p's: ``--law none --restoring 0.8`` (omega ~ U(0.785, 3.14) sqrt(0.8)).

Laws (c > 0 a friction): ``none``; ``viscous`` -c v; ``rational`` -c v / (1 + (v / v0)^2); ``tanh`` -c v0 tanh(v / v0);
``stribeck`` -c sign(v) (1 + ratio exp(-(v / v0)^2)); ``viscous_coulomb`` -c v - ratio sign(v); ``drag`` -c v |v|.
With ``--spread s``, each trajectory draws its own c from U(c - s, c + s): a friction that varies between units.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

LAWS = {
    "none": lambda v, c, v0, ratio: 0.0 * v,
    "viscous": lambda v, c, v0, ratio: -c * v,
    "rational": lambda v, c, v0, ratio: -c * v / (1 + (v / v0) ** 2),
    "tanh": lambda v, c, v0, ratio: -c * v0 * np.tanh(v / v0),
    "stribeck": lambda v, c, v0, ratio: -c * _sign(v) * (1 + ratio * np.exp(-((v / v0) ** 2))),
    "viscous_coulomb": lambda v, c, v0, ratio: -c * v - ratio * _sign(v),
    "drag": lambda v, c, v0, ratio: -c * v * np.abs(v),
}


SOLVER = {"rtol": 1e-9, "atol": 1e-11, "method": "DOP853"}


def _sign(v):
    """sign(v) smoothed over |v| < 1e-3 rad/s: a pendulum that comes to rest under dry friction makes an exact sign chatter,
    and the solver's steps shrink without end."""
    return np.tanh(v / 1e-3)


def write(
    path: Path,
    law: str,
    c: float,
    v0: float,
    ratio: float,
    n: int,
    seed: int,
    noise: float,
    restoring: float = 1.0,
    spread: float = 0.0,
) -> Path:
    """``n`` trajectories of the pendulum with the friction ``law`` (its c drawn per trajectory from U(c - ``spread``,
    c + ``spread``)) and its restoring force scaled by ``restoring`` (omega by its square root) written to the CSV
    file ``path``."""
    friction = LAWS[law]

    def draw(rng: np.random.Generator) -> Callable:
        own = c if spread == 0 else rng.uniform(c - spread, c + spread)  # constant c: no draw, the files of before
        return lambda _, v: friction(v, own, v0, ratio)

    path.write_text("\n".join(csv_rows(np.random.default_rng(seed), n, draw, noise, restoring=restoring)) + "\n")
    return path


def csv_rows(
    rng: np.random.Generator, n: int, draw_force: Callable, noise: float, record: bool = False, restoring: float = 1.0
) -> list[str]:
    """The CSV rows of ``n`` pendulums, each with its ``draw_force(rng)(t, velocity)`` added to d velocity/dt and omega
    scaled by sqrt(``restoring``): each trajectory's angle with white noise of sd ``noise`` and, with ``record``, its
    omega and x0."""
    t = np.arange(50) * 0.1

    def field(s, y, omega, force):
        return [y[1], -(omega**2) * np.sin(y[0]) + force(s, y[1])]

    rows = ["trajectory,t,angle" + (",omega,x0_angle,x0_velocity" if record else "")]
    for i in range(n):
        angle, omega = rng.uniform(-1.57, 1.57), rng.uniform(0.785, 3.14) * np.sqrt(restoring)
        force = draw_force(rng)
        solved = solve_ivp(field, (0, t[-1]), [angle, 0.0], t_eval=t, args=(omega, force), **SOLVER)
        measured = solved.y[0] + rng.normal(0, noise, len(t))
        inputs = f",{omega:.9g},{angle:.9g},0" if record else ""
        rows += [f"{i},{time:.10g},{value:.9g}{inputs}" for time, value in zip(t, measured)]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--law", choices=sorted(LAWS), required=True)
    parser.add_argument("--c", type=float, default=0.8)
    parser.add_argument("--v0", type=float, default=2.0)
    parser.add_argument("--ratio", type=float, default=1.0)
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise", type=float, default=0.02)
    parser.add_argument("--spread", type=float, default=0.0, help="c drawn per trajectory from U(c - spread, c + spread)")
    parser.add_argument("--restoring", type=float, default=1.0, help="the restoring force's scale (omega by its root)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    write(args.out, args.law, args.c, args.v0, args.ratio, args.n, args.seed, args.noise, args.restoring, args.spread)


if __name__ == "__main__":
    main()
