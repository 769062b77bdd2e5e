"""The library search of ``otgb discover`` alone, on one benchmark case's measured file, from f_phi's first model.

``otgb discover`` runs the library search (:mod:`otgb.discovery.search`) when the physics it
augmented along f_phi's route still disagrees with the measurements. On reaction-diffusion that
route is slow (f_phi is a constant plus many small terms: docs/discovery.md), so this script
starts the search where that route starts: ``--start`` (one term, f_phi's largest) fitted alone
by distribution matching. It writes ``search.json``: the search's path, the kept terms, the
held-out energy of the case's true hidden terms (for comparison) and the gap table on the test
measurements (f_p, f_p plus the kept terms, Reference). A finished search is kept when run again.

    python scripts/library_search.py --out bench/search --case reactdiff_reaction --start 1:u
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from discovery_benchmark import CASES, ROOT, export

from otgb.data import SimulationDataModule
from otgb.discovery.cli import DiscoverCLI
from otgb.discovery.library import Candidate, build_library
from otgb.discovery.refine import Fitting, discrepancies
from otgb.discovery.regression import design_matrix
from otgb.discovery.search import search
from otgb.discovery.workflow import DiscoverySettings, Measurements, acting_components, gap_step, simulate_from_priors
from otgb.physics import Augmented, Constant, LibraryTerm
from otgb.training import MapTraining


def natural_scales(physics, library: list[Candidate], size: float, seed: int) -> dict[Candidate, float]:
    """Per candidate, the coefficient at which its term alone is as large as ``size`` along f_p's trajectories
    (``otgb discover`` uses f_phi's size; here the first model's correction stands in for it)."""
    g = torch.Generator().manual_seed(seed)
    x0, theta = physics.sample_initial_state(64, g), physics.sample_theta(64, g)
    with torch.no_grad():
        states = physics.solve(physics.vector_field, x0, theta)
    scales = {}
    for component in dict.fromkeys(c.component for c in library):
        mine = [c for c in library if c.component == component]
        design = design_matrix(physics, mine, states, theta, torch.zeros(states[:, :, 0].shape), seed)
        scales.update({c: size / max(float(r), 1e-12) for c, r in zip(mine, design.scale)})
    return scales


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--case", default="reactdiff_reaction", choices=list(CASES))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--start", default="1:u", help="FEATURE:COMPONENT fitted first (f_phi's largest term)")
    parser.add_argument("--batch", type=int, default=256, help="simulations per distribution-matching fit")
    args = parser.parse_args()
    if args.start.count(":") != 1:
        parser.error(f"--start {args.start!r}: expected FEATURE:COMPONENT, e.g. 1:u or velocity:velocity")
    folder = args.out / f"{args.case}-seed{args.seed}"
    if not (folder / "measured.npz").exists():
        export(args.case, args.seed, 0.0, folder / "measured.npz")
    config, _, truth, *_ = CASES[args.case]
    measured = f"--data.measured_path={folder / 'measured.npz'}"
    cli = DiscoverCLI(
        MapTraining,
        SimulationDataModule,
        args=["--config", str(ROOT / "configs" / config), "--data.hidden_effect=[]", measured],
        run=False,
    )
    data, physics = Measurements.from_datamodule(cli.datamodule), cli.datamodule.physics
    path = folder / "search.json"
    summary = json.loads(path.read_text()) if path.exists() else run_search(physics, data, args, truth)
    if "gap" not in summary:  # a finished search is kept; the gap table is added to it
        summary["gap"] = gap(physics, data, summary["kept"], args.seed)
    path.write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))


def run_search(physics, data: Measurements, args: argparse.Namespace, truth: list) -> dict:
    library = build_library(physics, acting_components(physics))
    first_term = Candidate(*args.start.split(":"))
    if first_term not in library:
        example = f"{library[0].feature}:{library[0].component}"
        raise SystemExit(f"library_search.py: --start {args.start!r} is not a candidate of this model; e.g. {example}")
    fitting = Fitting(physics, data.train, data.val, 50, args.batch, args.seed)
    started = time.time()
    first = fitting([first_term], [0.0]).priors[0].value
    fitting.natural = natural_scales(physics, library, max(abs(first), 1e-3), args.seed)
    kept, path = search(
        library, [first if c == first_term else 0.0 for c in library], fitting,
        lambda m: print(f"[{time.time() - started:.0f} s] {m}", flush=True),
    )  # fmt: skip
    true_terms = [Candidate(t.feature, t.component) for t in truth]
    truth_score = discrepancies(physics, true_terms, [t.priors["coefficient"] for t in truth], data.val, args.seed)
    kept_terms = (kept.candidates, kept.priors) if kept else ([], [])
    return {
        "case": args.case,
        "start": {"feature": first_term.feature, "component": first_term.component, "coefficient": first},
        "kept": [{"feature": c.feature, "component": c.component, "coefficient": p.value} for c, p in zip(*kept_terms)],
        "kept_heldout_energy": kept.heldout_energy if kept else None,
        "path": [
            {
                "terms": [f"{c.feature} on d{c.component}/dt" for c in step.candidates],
                "heldout_energy": step.fitted.heldout_energy,
                "alternatives": [[c.feature for c in a] for a in step.alternatives],
            }
            for step in path
        ],
        "truth_heldout_energy": truth_score.mean,
        "wall_s": time.time() - started,
    }


def gap(physics, data: Measurements, kept: list[dict], seed: int) -> dict:
    """MMD, C2ST and energy distance on the test measurements of f_p and of f_p plus the kept terms, and the Reference."""
    terms = [LibraryTerm(t["feature"], t["component"], Constant(t["coefficient"])) for t in kept]
    sources = {"f_p": simulate_from_priors(physics, len(data.test), seed, "gap-f_p")}
    if terms:
        sources["augmented"] = simulate_from_priors(Augmented(physics, terms), len(data.test), seed, "gap-augmented")
    return gap_step(sources, data.test, DiscoverySettings(seed=seed))


if __name__ == "__main__":
    main()
