"""Where a one-to-many map's draws differ from the measured ones: spread, bias and C2ST per frame.

    python scripts/one_to_many_diagnostics.py --config configs/pendulum_2m.yaml \
        --ckpt_path runs/pendulum_2m/version_0/checkpoints/best-...ckpt --out docs/figures/pendulum_2m_frames.png

On the config's joint test set (each input (theta, x0) with several DGP draws y), the map is
drawn as often per input, and per observed frame t:

- **spread**: the std over the draws of one input, averaged over inputs (and grid cells), for
  the measured draws and the map's ("Hybrid Generative Modeling for Incomplete Physics: Deep
  Grey-Box Meets Optimal Transport" asks the map to reproduce the conditional distribution
  of y given the inputs, so its spread over z should match the process's spread);
- **bias**: the mean over inputs of |mean of the map's draws - mean of the measured draws|;
- **bias / spread**: the same per input and grid cell, in units of the measured draws' own
  spread there (a judge finds a bias of a few spreads at once, however small in the field's
  units; for fields it is also drawn over (t, grid cell));
- **C2ST**: the classifier two-sample test (:func:`otgb.metrics.c2st`, MLP judge, folds grouped
  by input) on rows (theta, x0, y_t) of that frame alone.

A whole-trajectory C2ST near 1 with per-frame C2STs near 0.5 says the judge reads the joint
shape over time; one frame near 1 says where the evidence is. Prints a Markdown table and draws
the three curves into ``--out``. Any further ``--key value`` overrides the config, as in ``otgb``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from otgb.cli import OTGBCLI  # noqa: E402
from otgb.data import SimulationDataModule  # noqa: E402
from otgb.metrics.c2st import c2st  # noqa: E402
from otgb.metrics.samples import joint_samples  # noqa: E402
from otgb.training import MapTraining  # noqa: E402


@torch.no_grad()
def map_draws(model: MapTraining, data: dict[str, torch.Tensor], n_draws: int, chunk: int = 64) -> torch.Tensor:
    parts = [
        model.generate(data["x"][i : i + chunk], data["x0"][i : i + chunk], data["theta"][i : i + chunk], n_draws)
        for i in range(0, len(data["x"]), chunk)
    ]
    return torch.cat(parts)


def whole(measured: torch.Tensor, drawn: torch.Tensor, data: dict[str, torch.Tensor], seed: int) -> float:
    """The same judge on whole trajectories (theta, x0, y)."""
    p, q = (joint_samples(data["theta"], data["x0"], y).float() for y in (measured, drawn))
    return float(c2st(p, q, folds=5, seed=seed, classifier="mlp", trajectory_shape=tuple(measured.shape[2:]))["c2st"])


def standardised_bias(measured: torch.Tensor, drawn: torch.Tensor) -> torch.Tensor:
    """|mean map - mean measured| over the draws of each input, in measured spreads, averaged over inputs: (T, *obs)."""
    spread = measured.std(1).clamp_min(1e-12)
    return ((drawn.mean(1) - measured.mean(1)).abs() / spread).mean(0)


def per_frame(measured: torch.Tensor, drawn: torch.Tensor, data: dict[str, torch.Tensor], seed: int) -> list[dict]:
    """Spread, bias and C2ST of each frame; measured and drawn are (N, M, T, *obs)."""
    rows = []
    for t in range(measured.shape[2]):
        a, b = measured[:, :, t : t + 1], drawn[:, :, t : t + 1]
        judge = c2st(
            joint_samples(data["theta"], data["x0"], a).float(),
            joint_samples(data["theta"], data["x0"], b).float(),
            folds=5, seed=seed, classifier="mlp", trajectory_shape=tuple(a.shape[2:]),
        )  # fmt: skip
        rows.append(
            {
                "frame": t,
                "spread_measured": float(a.std(1).mean()),
                "spread_map": float(b.std(1).mean()),
                "bias": float((a.mean(1) - b.mean(1)).abs().mean()),
                "bias_in_spreads": float(standardised_bias(a, b).mean()),
                "c2st": float(judge["c2st"]),
            }
        )
    return rows


def figure(rows: list[dict], times: torch.Tensor, ratio: torch.Tensor, title: str, out: Path) -> None:
    cells = ratio.reshape(len(ratio), -1)  # (T, observed values of a frame)
    field = cells.shape[1] > 3  # fields get a third panel over (t, grid cell)
    fig, axes = plt.subplots(1, 3 if field else 2, figsize=(15 if field else 10, 3.5))
    t = times.tolist()
    axes[0].plot(t, [r["spread_measured"] for r in rows], label="measured (DGP draws)")
    axes[0].plot(t, [r["spread_map"] for r in rows], label="map (z draws)")
    axes[0].plot(t, [r["bias"] for r in rows], "--", label="|mean map - mean measured|")
    axes[0].set(xlabel="t", ylabel="per-input std over draws", title="spread over time")
    axes[0].legend()
    axes[1].plot(t, [r["c2st"] for r in rows], "o-")
    axes[1].axhline(0.5, color="grey", lw=0.8)
    axes[1].set(xlabel="t", ylabel="C2ST accuracy", ylim=(0.4, 1.0), title="C2ST on one frame (theta, x0, y_t)")
    if field:
        image = axes[2].imshow(cells.T, aspect="auto", origin="lower", extent=(t[0], t[-1], 0, cells.shape[1]))
        axes[2].set(xlabel="t", ylabel="grid cell", title="|mean map - mean measured| / measured spread")
        fig.colorbar(image, ax=axes[2])
    fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="the run's config (a one-to-many task: data.draws_per_input > 1)")
    parser.add_argument("--ckpt_path", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True, help="the figure (PNG)")
    parser.add_argument("--seed", type=int, default=0)
    args, overrides = parser.parse_known_args()
    if not args.ckpt_path.is_file():
        raise SystemExit(f"--ckpt_path {args.ckpt_path}: no such checkpoint file")
    arguments = ["--config", args.config, "--trainer.logger=false", *overrides]
    cli = OTGBCLI(MapTraining, SimulationDataModule, run=False, args=arguments)
    model, datamodule = cli.model, cli.datamodule
    model.load_state_dict(torch.load(args.ckpt_path, map_location="cpu", weights_only=False)["state_dict"])
    model.eval()
    datamodule.setup("test")
    data = datamodule.test_set
    measured = data["y"]
    if measured.shape[1] < 2:
        raise SystemExit(f"{args.config}: the test set has one draw per input; the spread needs data.draws_per_input > 1")
    drawn = map_draws(model, data, measured.shape[1])
    print(f"{args.config}, {args.ckpt_path.name}: {len(measured)} test inputs x {measured.shape[1]} draws", flush=True)
    rows = per_frame(measured, drawn, data, args.seed)
    times = datamodule.physics.observation_times()[-measured.shape[2] :]
    print("| t | spread measured | spread map | bias | bias / spread | C2ST (this frame) |\n|---|---|---|---|---|---|")
    for r, t in zip(rows, times.tolist()):
        spread = f"{r['spread_measured']:.4f} | {r['spread_map']:.4f}"
        print(f"| {t:.3g} | {spread} | {r['bias']:.4f} | {r['bias_in_spreads']:.2f} | {r['c2st']:.3f} |")
    ratio = standardised_bias(measured, drawn)
    if ratio[0].numel() > 3:
        per_cell = ratio.reshape(len(ratio), -1).mean(0)
        print("bias / spread per grid cell (mean over frames):", " ".join(f"{v:.2f}" for v in per_cell.tolist()))
    figure(rows, times, ratio, f"{Path(args.config).stem}: {args.ckpt_path.name}", args.out)
    print(f"figure: {args.out}", flush=True)
    print(f"C2ST on whole trajectories, the same MLP judge: {whole(measured, drawn, data, args.seed):.3f}")


if __name__ == "__main__":
    main()
