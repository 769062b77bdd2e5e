"""The verification on the test part, which no fit saw: the gap table, the test of which model is nearer, and the
paired check on recorded inputs."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from otgb.data.gaps import filled, with_gaps_of
from otgb.discovery.closer import Closeness, closer
from otgb.discovery.draws import at_most, simulate_candidate, simulate_from_priors
from otgb.discovery.families import varies
from otgb.discovery.paired import PairedCheck, paired_check
from otgb.discovery.refine import FittedTerms
from otgb.discovery.seeds import Seeds, stream
from otgb.discovery.settings import DiscoverySettings, Measurements
from otgb.discovery.stages import stage
from otgb.metrics.c2st import c2st
from otgb.metrics.energy import energy_distance
from otgb.metrics.mmd import mmd_multiscale
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel


@stage("verification on the test part")
def gap_step(sources: dict[str, Tensor], test: Tensor, settings: DiscoverySettings, seeds: Seeds) -> dict[str, dict[str, float]]:
    """MMD, C2ST and energy distance of each source's draws against the test measurements, and the Reference (one
    random half of the test part against the other). Where test values are missing (NaN), each source's draws take the
    test part's gaps (:mod:`otgb.data.gaps`); the Reference's halves have theirs."""
    gap = {name: scores(with_gaps_of(draws, test), test, settings.c2st_classifier, seeds) for name, draws in sources.items()}
    order = torch.randperm(len(test), generator=stream(seeds.root))
    half = len(test) // 2
    gap["reference"] = scores(test[order[:half]], test[order[half : 2 * half]], settings.c2st_classifier, seeds)
    return gap


def scores(p: Tensor, q: Tensor, classifier: str, seeds: Seeds) -> dict[str, float]:
    """MMD, C2ST and energy distance of two samples, a missing value (NaN) 0 in both."""
    shape = tuple(p.shape[1:])
    p, q = filled(p.flatten(1).double()), filled(q.flatten(1).double())
    judge = c2st(p.float(), q.float(), folds=5, seed=seeds.root, classifier=classifier, trajectory_shape=shape)
    return {
        "mmd": float(mmd_multiscale(p, q)),
        "c2st": float(judge["c2st"]),
        "c2st_std": float(judge["c2st_std"]),
        "energy": float(energy_distance(p, q)),
    }


CLOSER_DRAWS = 4  # trajectories of each model per test trajectory in the test of which is nearer: more draws, more power


def closer_step(
    model: Augmented, physics: PhysicsModel, test: Tensor, settings: DiscoverySettings, seeds: Seeds
) -> Closeness | None:
    """Whether the augmented physics ``model`` is nearer to the test measurements (at most ``locate_rows`` of them,
    drawn at random) than f_p alone (:mod:`.closer`), on fresh draws of both: ``CLOSER_DRAWS`` per test trajectory, at
    most ``locate_rows`` and at least as many as the test trajectories. None where too few trajectories of either
    model stay finite to test (the augmented physics's divergences are logged and counted against it)."""
    tests = settings.tests
    tested = at_most(test, tests.locate_rows, seeds)
    n = max(len(tested), min(CLOSER_DRAWS * len(tested), tests.locate_rows))
    augmented = simulate_candidate(model, n, seeds, "closer-augmented")
    f_p = simulate_from_priors(physics, n, seeds, "closer-f_p")
    try:
        return closer(augmented, f_p, tested, tests.n_permutations, tests.alpha, seeds.root, n - len(augmented))
    except ValueError:  # too few finite trajectories: the verdict says no test could run
        return None


@stage("paired check")
def paired_after(fitted: FittedTerms, physics: PhysicsModel, data: Measurements, alpha: float) -> PairedCheck | None:
    """The named terms' paired check on the test part at level ``alpha``, where it applies: recorded inputs, a given
    noise and constant coefficients (with a spread, a coefficient per trajectory is unknown and nothing pairs)."""
    if not data.pairable() or varies(fitted.family):
        return None
    model, (x0, theta) = fitted.model(physics), data.test_inputs
    coefficients = model.sample_theta(len(theta), torch.Generator())[:, theta.shape[1] :]  # constants: the same each row
    names = {"model": "the augmented physics", "part": "the test part's"}
    check = paired_check(model, data.test, x0, torch.cat([theta, coefficients], dim=1), data.noise, data.test_signals, **names)
    return replace(check, significant=check.pvalue < alpha)


def c2st_tells_apart(gap: dict[str, dict[str, float]], source: str) -> str | None:
    """Where the gap table's C2ST tells ``source``'s draws from the test measurements, its accuracy above 0.5 by more
    than two of the Reference's standard deviations (half the test measurements against the other half, repeated),
    the numbers that say so; else None (also where either figure is missing or not finite)."""
    judged, reference = gap.get(source, {}), gap.get("reference", {})
    if "c2st" not in judged or "c2st_std" not in reference or not judged["c2st"] - 0.5 > 2 * reference["c2st_std"]:
        return None
    return c2st_numbers(gap, source)


def c2st_numbers(gap: dict[str, dict[str, float]], source: str) -> str | None:
    """``source``'s C2ST beside the Reference's, as the verdict quotes them; None where either is missing."""
    judged, reference = gap.get(source, {}), gap.get("reference", {})
    if "c2st" not in judged or "c2st_std" not in reference:
        return None
    return f"C2ST {judged['c2st']:.2f}, the Reference's {reference['c2st']:.2f} +- {reference['c2st_std']:.2f}"
