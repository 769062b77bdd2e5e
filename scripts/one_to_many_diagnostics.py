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
shape over time; one frame near 1 says where the evidence is. The variance share along each
input's leading direction says whether the draws of one input vary along one curve, as draws of
one random coefficient do, or in several directions; the |cos| between the map's and the
measured leading directions, whether that curve is the measured one. Prints a Markdown table and draws
the three curves into ``--out``; then the C2ST on whole trajectories with each of ``--judges``
("auto" is the evaluation's own judge). Any further ``--key value`` overrides the config, as in
``otgb``. Without ``--ckpt_path`` the config's map is used untrained: a map with nothing to learn
measures how strong the judge is, e.g. the DGP's own simulator with a hidden effect slightly off:

    python scripts/one_to_many_diagnostics.py --config configs/advdiff_mm.yaml --no-per_frame \
        --model.transport_map=otgb.models.CompletePhysicsMap \
        '--model.transport_map.init_args.hidden_effect=[{class_path: otgb.physics.Advection, init_args: {beta:
        {class_path: otgb.physics.Uniform, init_args: {low: 0.0105, high: 0.105}}}}]'
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from otgb.analysis.figures import save  # noqa: E402
from otgb.metrics.c2st import c2st  # noqa: E402
from otgb.metrics.samples import joint_samples  # noqa: E402
from otgb.physics import PhysicsModel  # noqa: E402
from otgb.runs import load_run  # noqa: E402
from otgb.training import MapTraining  # noqa: E402


@torch.no_grad()
def map_draws(model: MapTraining, data: dict[str, torch.Tensor], n_draws: int, chunk: int = 64) -> torch.Tensor:
    parts = [
        model.generate(data["x"][i : i + chunk], data["x0"][i : i + chunk], data["theta"][i : i + chunk], n_draws)
        for i in range(0, len(data["x"]), chunk)
    ]
    return torch.cat(parts)


def whole(measured: torch.Tensor, drawn: torch.Tensor, data: dict[str, torch.Tensor], seed: int, judge: str) -> float:
    """C2ST on whole trajectories (theta, x0, y) with ``judge`` ("auto" is the evaluation's: an MLP, or a conv net for fields)."""
    p, q = (joint_samples(data["theta"], data["x0"], y).float() for y in (measured, drawn))
    return float(c2st(p, q, folds=5, seed=seed, classifier=judge, trajectory_shape=tuple(measured.shape[2:]))["c2st"])


def standardised_bias(measured: torch.Tensor, drawn: torch.Tensor) -> torch.Tensor:
    """|mean map - mean measured| over the draws of each input, in measured spreads, averaged over inputs: (T, *obs).

    Values the measured draws share exactly (no spread: the initial state, a Dirichlet end) are NaN."""
    spread = measured.std(1)
    ratio = (drawn.mean(1) - measured.mean(1)).abs() / spread
    return torch.where(spread > 1e-9, ratio, torch.nan).nanmean(0)


def leading_direction_share(draws: torch.Tensor) -> float:
    """Share of the draws' variance, per input, along their leading direction: mean over inputs, (N, M, ...) draws.

    Draws that vary with one random coefficient (beta of an advection, a friction value) lie near
    one curve through the space of trajectories, so the share is near 1; draws that a latent moves
    in several independent directions have a lower share, even with the same spread per value."""
    power = torch.linalg.svdvals(centred(draws)) ** 2
    return float((power[:, 0] / power.sum(1).clamp_min(1e-300)).mean())


def leading_direction_alignment(measured: torch.Tensor, drawn: torch.Tensor) -> float:
    """|cos| between the measured draws' and the map's leading directions, per input: mean over inputs.

    1 when the map's draws of an input vary along the same direction as the measured ones (the
    right curve); a share near 1 with a low alignment is one curve, but the wrong one."""

    def leading(draws: torch.Tensor) -> torch.Tensor:
        return torch.linalg.svd(centred(draws), full_matrices=False).Vh[:, 0]

    return float((leading(measured) * leading(drawn)).sum(1).abs().mean())


def centred(draws: torch.Tensor) -> torch.Tensor:
    """(N, M, features) in float64: each input's M draws, flattened, minus their mean."""
    flat = draws.flatten(2).double()
    return flat - flat.mean(1, keepdim=True)


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
                "bias_in_spreads": float(standardised_bias(a, b).nanmean()),
                "c2st": float(judge["c2st"]),
            }
        )
    return rows


def figure(rows: list[dict], times: torch.Tensor, ratio: torch.Tensor, title: str, out: Path, time_label: str) -> None:
    cells = ratio.reshape(len(ratio), -1)  # (T, observed values of a frame)
    field = cells.shape[1] > 3  # fields get a third panel over (t, grid cell)
    fig, axes = plt.subplots(1, 3 if field else 2, figsize=(15 if field else 10, 3.5))
    t = times.tolist()
    axes[0].plot(t, [r["spread_measured"] for r in rows], label="measured (DGP draws)")
    axes[0].plot(t, [r["spread_map"] for r in rows], label="map (z draws)")
    axes[0].plot(t, [r["bias"] for r in rows], "--", label="|mean map - mean measured|")
    axes[0].set(xlabel=time_label, ylabel="per-input std over draws", title="spread over time")
    axes[0].legend()
    axes[1].plot(t, [r["c2st"] for r in rows], "o-")
    axes[1].axhline(0.5, color="grey", lw=0.8)
    axes[1].set(xlabel=time_label, ylabel="C2ST accuracy", ylim=(0.4, 1.0), title="C2ST on one frame (theta, x0, y_t)")
    if field:
        image = axes[2].imshow(cells.T, aspect="auto", origin="lower", extent=(t[0], t[-1], 0, cells.shape[1]))
        axes[2].set(xlabel=time_label, ylabel="grid cell", title="|mean map - mean measured| / measured spread")
        fig.colorbar(image, ax=axes[2])
    fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    save(fig, out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--config", required=True, action="append", help="config files, in order (one-to-many: data.draws_per_input > 1)"
    )
    parser.add_argument("--ckpt_path", type=Path, help="the trained map (none for a map with nothing to learn)")
    parser.add_argument("--out", type=Path, help="the figure (PNG), with --per_frame")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--per_frame", action=argparse.BooleanOptionalAction, default=True, help="per-frame table and figure")
    parser.add_argument(
        "--judges", nargs="*", default=["auto"], help="whole-trajectory C2ST judges (auto, mlp, conv, paper; none: --judges)"
    )
    args, overrides = parser.parse_known_args()
    if args.per_frame and args.out is None:
        raise SystemExit("--out: the per-frame figure needs a PNG path (or --no-per_frame)")
    if args.ckpt_path is not None and not args.ckpt_path.is_file():
        raise SystemExit(f"--ckpt_path {args.ckpt_path}: no such checkpoint file")
    run = load_run(args.config, "--trainer.logger=false", *overrides, ckpt_path=args.ckpt_path)
    model, datamodule = run.model, run.datamodule
    model.eval()
    datamodule.setup("test")
    data = datamodule.test_set
    measured = data["y"]
    if measured.shape[1] < 2:
        configs = " + ".join(args.config)
        raise SystemExit(f"{configs}: the test set has one draw per input; the spread needs data.draws_per_input > 1")
    drawn = map_draws(model, data, measured.shape[1])
    name = args.ckpt_path.name if args.ckpt_path else type(model.transport_map).__name__
    print(f"{' + '.join(args.config)}, {name}: {len(measured)} test inputs x {measured.shape[1]} draws", flush=True)
    ratio = standardised_bias(measured, drawn)
    print(f"bias / spread, mean over inputs, frames and cells with a measured spread: {float(ratio.nanmean()):.2f}")
    print(f"spread map / measured, mean over frames: {float(drawn.std(1).mean() / measured.std(1).mean()):.3f}")
    shares = f"measured {leading_direction_share(measured):.3f}, map {leading_direction_share(drawn):.3f}"
    print(f"variance share along each input's leading direction (whole trajectories): {shares}")
    print(f"|cos| between the map's and the measured leading directions: {leading_direction_alignment(measured, drawn):.3f}")
    if args.per_frame:
        table_and_figure(measured, drawn, data, ratio, datamodule.physics, args, name)
    for judge in args.judges:
        print(f"C2ST on whole trajectories, {judge} judge: {whole(measured, drawn, data, args.seed, judge):.3f}", flush=True)


def table_and_figure(
    measured: torch.Tensor,
    drawn: torch.Tensor,
    data: dict[str, torch.Tensor],
    ratio: torch.Tensor,
    physics: PhysicsModel,
    args: argparse.Namespace,
    name: str,
) -> None:
    """Per frame: spread, bias and C2ST printed as Markdown; the curves (and the bias map of a field) into ``--out``."""
    rows = per_frame(measured, drawn, data, args.seed)
    times = physics.observation_times()[-measured.shape[2] :]
    print("| t | spread measured | spread map | bias | bias / spread | C2ST (this frame) |\n|---|---|---|---|---|---|")
    for r, t in zip(rows, times.tolist()):
        spread = f"{r['spread_measured']:.4f} | {r['spread_map']:.4f}"
        print(f"| {t:.3g} | {spread} | {r['bias']:.4f} | {r['bias_in_spreads']:.2f} | {r['c2st']:.3f} |")
    if ratio[0].numel() > 3:
        per_cell = ratio.reshape(len(ratio), -1).nanmean(0)
        print("bias / spread per grid cell (mean over frames):", " ".join(f"{v:.2f}" for v in per_cell.tolist()))
    title = f"{'-'.join(Path(path).stem for path in args.config)}: {name}"
    figure(rows, times, ratio, title, args.out, physics.axis_label("t"))
    print(f"figure: {args.out}", flush=True)


if __name__ == "__main__":
    main()
