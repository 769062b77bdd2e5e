"""How well do measured trajectories pin the range of a friction that varies between them?

The DGP is the pendulum with a viscous friction whose coefficient is U(-1.5, -0.6) per
trajectory (range 0.9). The right term (velocity on dvelocity/dt) is given; only its uniform
prior is fitted by distribution matching (:func:`otgb.discovery.refine.fit`), on independent
measured sets of ``--n`` trajectories and with different simulation samples, so that the spread
of the fitted width splits into the measured sample's part and the simulation sample's part.

    python scripts/stochastic_width.py --n 700 --sets 1 2 --fits 0:1024 1:1024 0:4096 --out width.json
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from otgb.data import generate_measured
from otgb.discovery.library import build_library
from otgb.discovery.refine import fit
from otgb.physics import LibraryTerm, Pendulum, Uniform


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=700, help="measured trajectories per set (the training part)")
    parser.add_argument("--sets", type=int, nargs="+", default=[1, 2], help="seeds of the measured sets")
    parser.add_argument("--fits", nargs="+", default=["0:1024", "1:1024"], help="seed:batch of each fit's simulation sample")
    parser.add_argument("--out", default="width.json")
    args = parser.parse_args()
    pendulum = Pendulum()
    dgp = pendulum.with_hidden_effect([LibraryTerm("velocity", "velocity", Uniform(-1.5, -0.6))])
    velocity = next(c for c in build_library(pendulum, ["velocity"]) if c.feature == "velocity")
    results = []
    for data_seed in args.sets:
        train = torch.as_tensor(generate_measured(dgp, args.n, data_seed)["y"]).float()
        val = torch.as_tensor(generate_measured(dgp, 150, 50 + data_seed)["y"]).float()
        for spec in args.fits:
            seed, batch = map(int, spec.split(":"))
            start = time.time()
            prior = fit(pendulum, [velocity], [-1.0], "uniform", train, val, batch=batch, seed=seed, score=False).priors[0]
            results.append({"set": data_seed, "fit_seed": seed, "batch": batch, "low": prior.low, "high": prior.high,
                            "width": prior.high - prior.low, "seconds": time.time() - start})  # fmt: skip
            print(results[-1], flush=True)
    with open(args.out, "w") as f:
        json.dump({"truth": {"low": -1.5, "high": -0.6, "width": 0.9}, "fits": results}, f, indent=1)


if __name__ == "__main__":
    main()
