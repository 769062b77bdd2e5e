"""Write a config's synthetic measurements (physics + data.hidden_effect) to a file, as an experiment would.

    python scripts/export_measured.py --config configs/pendulum.yaml --out friction.npz
    python scripts/export_measured.py --config configs/pendulum.yaml --out friction.csv --record theta
    python scripts/export_measured.py --config configs/pendulum.yaml --out noisy.npz --noise 0.05

The file holds the DGP's trajectories ``y`` and the time grid ``t``, and with ``--record``
the inputs each trajectory was simulated with (``theta``, ``x0``), in the layout that
``data.measured_path`` reads (otgb.data.files): a stand-in for real measurements in which
the hidden effect is known, to check what the measured-data mode finds. The draws are those
of the config's generated measured set (``data.seed``, ``data.n_measured`` or ``--n``); ``--noise SD``
adds white Gaussian noise of that standard deviation to every value (seeded by ``data.seed``), as a
sensor would (give the same SD as ``data.measurement_noise`` when fitting them).
An existing file is never overwritten.
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import numpy as np

from otgb.data import generate_measured
from otgb.data.measured import with_measurement_noise
from otgb.data.seeding import generator_for
from otgb.runs import load_run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="a config with data.physics and data.hidden_effect")
    parser.add_argument("--out", required=True, type=Path, help="the file to write: .npz or .csv")
    parser.add_argument("--n", type=int, default=None, help="trajectories (default: the config's data.n_measured)")
    parser.add_argument("--record", nargs="*", default=[], choices=["theta", "x0"], help="inputs to record per trajectory")
    parser.add_argument("--noise", type=float, default=0.0, help="sd of white noise added to every measured value")
    args, overrides = parser.parse_known_args()
    if args.out.exists():
        raise SystemExit(f"export_measured: {args.out} exists; it is never overwritten")
    if args.out.suffix not in (".npz", ".csv"):
        raise SystemExit(f"export_measured: --out {args.out}: expected a .npz or .csv file")
    if not (math.isfinite(args.noise) and args.noise >= 0):
        raise SystemExit(f"export_measured: --noise {args.noise}: expected a standard deviation >= 0")
    data = load_run(args.config, *overrides).datamodule
    sets = generate_measured(data.dgp, args.n or data.n_measured, data.seed)
    times = data.physics.observation_times().double().numpy().round(9)
    y = with_measurement_noise(sets["y"], args.noise, generator_for(data.seed, "export", "noise"))
    content = {"y": y.numpy(), "t": times}
    content.update({name: sets[name].numpy() for name in args.record})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    (write_csv if args.out.suffix == ".csv" else write_npz)(args.out, content, data.physics)
    noise = f", white noise of sd {args.noise:g} added" if args.noise else ""
    print(f"wrote {args.out}: {len(y)} trajectories of shape {tuple(y.shape[1:])}, recorded {args.record}{noise}")


def write_npz(path: Path, content: dict[str, np.ndarray], physics) -> None:
    np.savez(path, **content)


def write_csv(path: Path, content: dict[str, np.ndarray], physics) -> None:
    """The long layout: trajectory, t, <observed>[, <theta names>][, x0_<state names>]."""
    y, t = content["y"], content["t"]
    if y.ndim != 3:
        raise SystemExit(f"export_measured: CSV holds low-dimensional series; trajectories {y.shape[1:]} need .npz")
    header = ["trajectory", "t", *physics.observed]
    per_trajectory = []
    if "theta" in content:
        header += list(physics.theta_names)
        per_trajectory.append(content["theta"])
    if "x0" in content:
        header += [f"x0_{name}" for name in physics.state_names]
        per_trajectory.append(content["x0"].reshape(len(y), -1))
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        for i in range(len(y)):
            extra = [f"{v:.9g}" for block in per_trajectory for v in block[i]]  # 9 digits: float32 exactly
            for k, time in enumerate(t):
                writer.writerow([i, f"{time:.9g}", *(f"{v:.9g}" for v in y[i, k]), *extra])


if __name__ == "__main__":
    main()
