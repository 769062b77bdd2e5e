"""A pendulum file as a lab records it, from an independent solver (SciPy's ``solve_ivp``, DOP853): a camera's frames.

The pendulum of ``configs/pendulum.yaml`` (omega ~ U(0.785, 3.14) rad/s, released at rest from an angle ~ U(-1.57,
1.57) rad) with a viscous friction -c v that otgb is not told, filmed at ``--rate`` frames per second from t = 0 for a
duration ~ U(3, 4.9) s per trajectory; a share ``--missing`` of the frames is lost at random, each lost frame either left
out of the file or written with an empty cell (one or the other at random, as loggers do both). The angle carries white
noise of sd ``--noise``; the file holds ``trajectory``, ``t`` and ``angle`` only (theta and x0 not recorded)::

    python scripts/scipy_lab_pendulum.py --n 1000 --rate 30 --missing 0.2 --seed 0 --out lab.csv

``--drive A`` drives each pendulum with an angular acceleration, a sum of two sines of its own (amplitudes ~ U(0, A)
rad/s^2, frequencies ~ U(0.2, 1) Hz, phases ~ U(0, 2 pi)), recorded in a ``drive`` column at every written frame (a
lost frame's drive is logged even where its angle is not)::

    python scripts/scipy_lab_pendulum.py --n 1000 --rate 30 --missing 0.2 --drive 1.0 --seed 0 --out driven.csv
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

SOLVER = {"rtol": 1e-9, "atol": 1e-11, "method": "DOP853"}
DURATION = (3.0, 4.9)  # seconds filmed per trajectory, drawn uniformly; 4.9 s is the model's horizon


def lab_rows(
    rng: np.random.Generator, n: int, c: float, rate: float, missing: float, noise: float, drive: float = 0.0
) -> list[str]:  # fmt: skip
    """The CSV rows of ``n`` filmed pendulums with viscous friction ``c``, driven where ``drive`` > 0 (the module
    docstring)."""

    def field(time, y, omega, sines):
        return [y[1], -(omega**2) * np.sin(y[0]) - c * y[1] + acceleration(sines, time)]

    rows = ["trajectory,t,angle,drive" if drive > 0 else "trajectory,t,angle"]
    for i in range(n):
        angle, omega = rng.uniform(-1.57, 1.57), rng.uniform(0.785, 3.14)
        duration = rng.uniform(*DURATION)
        sines = (rng.uniform(0, drive, 2), rng.uniform(0.2, 1.0, 2), rng.uniform(0, 2 * np.pi, 2)) if drive > 0 else None
        t = np.arange(int(np.floor(duration * rate + 1e-9)) + 1) / rate
        solved = solve_ivp(field, (0, t[-1]), [angle, 0.0], t_eval=t, args=(omega, sines), **SOLVER)
        measured = solved.y[0] + rng.normal(0, noise, len(t))
        lost, written_empty = rng.random(len(t)) < missing, rng.random(len(t)) < 0.5
        logged = [f",{acceleration(sines, time):.9g}" if sines else "" for time in t]
        for time, value, gone, empty, u in zip(t, measured, lost, written_empty, logged):
            if not gone:
                rows.append(f"{i},{time:.10g},{value:.9g}{u}")
            elif empty:
                rows.append(f"{i},{time:.10g},{u}")
    return rows


def acceleration(sines: tuple[np.ndarray, np.ndarray, np.ndarray] | None, time: float) -> float:
    """The drive at ``time``: sum of a_k sin(2 pi f_k t + phi_k) for ``sines`` = (a, f, phi); 0 without a drive."""
    if sines is None:
        return 0.0
    amplitude, frequency, phase = sines
    return float(np.sum(amplitude * np.sin(2 * np.pi * frequency * time + phase)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--c", type=float, default=0.8, help="the viscous friction otgb is not told")
    parser.add_argument("--rate", type=float, default=30.0, help="frames per second")
    parser.add_argument("--missing", type=float, default=0.2, help="share of the frames lost at random")
    parser.add_argument("--noise", type=float, default=0.02)
    parser.add_argument("--drive", type=float, default=0.0, help="largest amplitude of the drive's two sines (0: none)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    rows = lab_rows(np.random.default_rng(args.seed), args.n, args.c, args.rate, args.missing, args.noise, args.drive)
    args.out.write_text("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
