"""How far React-diff-1-m's one-to-one errors go with a constant correction alone.

    python scripts/mean_only_correction.py [--inputs 128] [--drains -0.10 -0.15 -0.19 -0.22 -0.25]

``configs/reactdiff.yaml``'s f_p lacks the whole u-reaction u - u^3 - v - k. This script
scores f_p plus a constant drain c on du/dt (no dependence on the state at all) against the
data-generating process on the same inputs (x0, a, b from the priors), with the one-to-one
metrics of "Hybrid Generative Modeling for Incomplete Physics: Deep Grey-Box Meets Optimal
Transport" (ABS ERR, N-RMSE; :mod:`otgb.metrics.errors`). The DGP is solved as the config
makes its measurements (RK4 at step 1e-3), the models at the training solver's step (0.1).

If a constant reaches the errors of a trained grey-box, those errors do not show that the
grey-box learned the reaction's shape; docs/discovery.md uses this to read the React-diff runs.
"""

from __future__ import annotations

import argparse

import torch

from otgb.metrics.errors import abs_err, nrmse
from otgb.physics import Augmented, Constant, FitzHughNagumoReaction, LibraryTerm, ReactionDiffusion


@torch.no_grad()
def observed(model, x0: torch.Tensor, theta: torch.Tensor, effect_params: torch.Tensor | None = None) -> torch.Tensor:
    return model.simulate(x0, theta, effect_params)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--inputs", type=int, default=128, help="inputs (x0, a, b) drawn from the priors")
    parser.add_argument("--drains", type=float, nargs="*", default=[-0.10, -0.15, -0.19, -0.22, -0.25])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    f_p = ReactionDiffusion()
    dgp = ReactionDiffusion(step_size=1e-3, hidden_effect=[FitzHughNagumoReaction(k=Constant(5e-3))])
    g = torch.Generator().manual_seed(args.seed)
    x0, theta = f_p.sample_initial_state(args.inputs, g), f_p.sample_theta(args.inputs, g)
    k = torch.full((args.inputs, 1), 5e-3)
    target = observed(dgp, x0, theta, k)
    value_range = target.max() - target.min()

    def row(name: str, prediction: torch.Tensor) -> None:
        a, n = abs_err(prediction, target), nrmse(prediction, target, value_range)
        print(f"| {name} | {n.mean():.4f} +- {n.std():.4f} | {a.mean():.4f} +- {a.std():.4f} |")

    print(f"React-diff-1-m, {args.inputs} inputs from the priors (seed {args.seed}), against the DGP")
    print("| model | N-RMSE | ABS ERR |\n|---|---|---|")
    row("f_p alone", observed(f_p, x0, theta))
    for c in args.drains:
        drained = Augmented(f_p, [LibraryTerm("1", "u", Constant(c))])
        row(f"f_p + ({c:g}) on du/dt", observed(drained, x0, torch.cat([theta, torch.full((args.inputs, 1), c)], dim=1)))
    complete = ReactionDiffusion(hidden_effect=[FitzHughNagumoReaction(k=Constant(5e-3))])
    row("complete physics (step 0.1)", observed(complete, x0, theta, k))


if __name__ == "__main__":
    main()
