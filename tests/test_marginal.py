"""The energy distance and the marginal evaluation: draws against held-out measurements."""

import math

import pytest
import torch
from scipy.spatial.distance import cdist

from otgb.data import generate_joint
from otgb.metrics.energy import EnergyDistance, batched_energy, energy_distance, energy_per_time, row_distance_sums
from otgb.metrics.joint import JointEvaluator, split_half_scores
from otgb.physics import Pendulum, Uniform, ViscousFriction


def test_energy_distance_matches_the_u_statistic_by_hand(generator):
    p, q = torch.randn(30, 3, generator=generator, dtype=torch.float64), torch.randn(40, 3, generator=generator).double() + 1
    n, m = len(p), len(q)
    by_hand = 2 * cdist(p, q).mean() - cdist(p, p).sum() / (n * (n - 1)) - cdist(q, q).sum() / (m * (m - 1))
    assert float(batched_energy(p[None], q[None])[0]) == pytest.approx(by_hand, rel=1e-7)


def test_one_feature_by_sorting_equals_the_u_statistic_by_hand_with_its_gradient(generator):
    """One feature per row takes the sorting path: its value (paired and not), its gradient and the per-row distance
    sums equal scipy's pairwise distances, with values far from zero (cancellation)."""
    p = (100 + 3 * torch.randn(2, 30, 1, generator=generator, dtype=torch.float64)).requires_grad_()
    q = 100.5 + torch.randn(2, 30, 1, generator=generator, dtype=torch.float64)
    n = p.shape[1]
    for g in range(2):
        a, b = p[g].detach().numpy(), q[g].numpy()
        cross = cdist(a, b)
        unpaired = 2 * cross.mean() - cdist(a, a).sum() / (n * (n - 1)) - cdist(b, b).sum() / (n * (n - 1))
        paired = unpaired + 2 * cross.mean() / (n - 1) - 2 * cross.trace() / (n * (n - 1))
        assert float(batched_energy(p, q)[g].detach()) == pytest.approx(unpaired, rel=1e-9)
        assert float(batched_energy(p, q, paired=True)[g].detach()) == pytest.approx(paired, rel=1e-9)
        assert row_distance_sums(p[g, :, 0], q[g, :, 0]).detach().numpy() == pytest.approx(cross.sum(0), rel=1e-12)
    (gradient,) = torch.autograd.grad(batched_energy(p, q).sum(), p)
    # the matrix path (the value twice: every distance times sqrt(2)), about 0: its matrix product loses digits at 100
    x, y = (p.detach() - 100).requires_grad_(), q - 100
    (by_matrix,) = torch.autograd.grad(batched_energy(torch.cat([x, x], -1), torch.cat([y, y], -1)).sum() / 2**0.5, x)
    assert torch.allclose(gradient, by_matrix, rtol=1e-9, atol=1e-12)


def test_energy_distance_is_unbiased_and_sees_a_shift(generator):
    """Equal distributions: 0 on average at any sample size (a V-statistic would sit at ~2 E|X-X'|/n)."""
    same = torch.stack(
        [energy_distance(torch.randn(20, 2, generator=generator), torch.randn(20, 2, generator=generator)) for _ in range(400)]
    )
    assert abs(float(same.mean())) < 3 * float(same.std()) / math.sqrt(len(same))
    shifted = energy_distance(torch.randn(200, 2, generator=generator), torch.randn(200, 2, generator=generator) + 1.0)
    assert shifted > 0.5 > 10 * abs(float(same.mean()))


def test_energy_per_time_locates_the_disagreement(generator):
    """Two samples of trajectories (T=10, C=2) that differ only in component 1 from step 6 on."""
    p = torch.randn(300, 10, 2, generator=generator)
    q = torch.randn(300, 10, 2, generator=generator)
    q[:, 6:, 1] += 1.5
    cond = torch.zeros(300, 3)
    per_time = energy_per_time(torch.cat([cond, p.flatten(1)], 1), torch.cat([cond, q.flatten(1)], 1), (10, 2))
    assert per_time.shape == (10, 2)
    assert per_time[6:, 1].min() > 10 * per_time[:6].abs().max() and per_time[:, 0].abs().max() < 0.05
    metric = EnergyDistance(trajectory_shape=(10, 2))
    metric.update(p.flatten(1), q.flatten(1))
    assert torch.allclose(metric.compute()["energy_per_time"], energy_per_time(p.flatten(1), q.flatten(1), (10, 2)))


@pytest.fixture(scope="module")
def friction_draws():
    """Two independent draw sets of the one-to-many friction pendulum on the same 400 inputs."""
    physics = Pendulum()
    dgp = physics.with_hidden_effect([ViscousFriction(Uniform(0.6, 1.5))])
    return generate_joint(physics, dgp, n=400, draws=1, seed=5, split="test")


def test_marginal_evaluation_separates_fp_from_the_reference(friction_draws):
    """Measured: DGP draws of the first 200 inputs; candidates: f_p or DGP draws of 200 other inputs."""
    measured = {k: v[:200] for k, v in friction_draws.items()}
    other = {k: v[200:] for k, v in friction_draws.items()}
    marginal = JointEvaluator((50, 1), inputs=(), paired=False, mmdagg_permutations=200)
    fp = marginal.evaluate(other["x"].unsqueeze(1), measured, tests=True, candidate=other)
    same = marginal.evaluate(other["y_ref"], measured, tests=True, candidate=other)
    reference = split_half_scores(marginal, measured, tests=True, repeats=3)
    assert "abs_err" not in fp, "nothing is paired in a marginal comparison"
    assert fp["mmdagg_reject"] == 1 and fp["c2st"] > 0.75 and fp["energy"] > 10 * abs(float(reference["energy"]))
    assert same["mmdagg_reject"] == 0 and abs(float(same["c2st"]) - 0.5) < 3 * 0.5 / math.sqrt(400)
    assert reference["mmdagg_reject"] <= 1 / 3 and fp["energy_per_time"].shape == (50, 1)
    assert fp["energy_per_time"][0, 0] < 0.01 < fp["energy_per_time"][-1, 0], "f_p agrees at t = 0 and drifts away"


def test_a_map_that_ignores_theta_is_caught_when_theta_is_recorded(friction_draws):
    """Right marginal, wrong conditional: the draws of other inputs, given to these thetas."""
    data = friction_draws
    ignores_theta = data["y_ref"][torch.randperm(400, generator=torch.Generator().manual_seed(0))]
    marginal = JointEvaluator((50, 1), inputs=(), paired=False, mmdagg_permutations=200)
    joint = JointEvaluator((50, 1), inputs=("theta",), paired=True, mmdagg_permutations=200)
    assert marginal.evaluate(ignores_theta, data, tests=True)["mmdagg_reject"] == 0, "marginally it looks right"
    caught = joint.evaluate(ignores_theta, data, tests=True)
    right = joint.evaluate(data["y_ref"], data, tests=True)
    assert caught["mmdagg_reject"] == 1 and caught["c2st"] > 0.6 and right["mmdagg_reject"] == 0
    assert "abs_err" not in caught, "x0 not recorded: the pairs are not determined"


def test_draws_on_the_measurements_own_inputs_are_scored_across_halves_as_the_reference(friction_draws):
    """A file that recorded each trajectory's inputs: the map's draws are made on the test part's own inputs. A map
    that reproduces each measurement (its twin plus noise of sd 0.002) scored against the whole sample looks better
    than the noise floor (C2ST below 0.5, energy below the Reference's), the dependence of twins, not a model
    better than the data. Across halves it scores as the Reference does, on the same splits: with the measurements
    themselves as draws, exactly the Reference's numbers."""
    data = {k: v[:30] for k, v in friction_draws.items()}  # a test part of 200 trajectories
    twins = data["y"] + 0.002 * torch.randn(data["y"].shape, generator=torch.Generator().manual_seed(1))
    whole = JointEvaluator((50, 1), inputs=(), paired=False, mmdagg_permutations=200)
    halves = JointEvaluator((50, 1), inputs=(), paired=False, mmdagg_permutations=200, across_halves=4)
    reference = split_half_scores(JointEvaluator((50, 1), inputs=(), paired=False, mmdagg_permutations=200), data, True, 4)
    biased = whole.evaluate(twins, data, tests=True)
    assert biased["c2st"] < 0.45 and biased["energy"] < reference["energy"] - 2 * reference["energy_std"]
    fair = halves.evaluate(data["y"], data, tests=True)
    for name in ("energy", "mmd", "mmd2_median", "c2st", "mmdagg_reject", "c2st_std", "energy_std"):
        assert torch.allclose(fair[name], reference[name]), name
    twin = halves.evaluate(twins, data, tests=True)
    assert abs(float(twin["energy"] - reference["energy"])) < 0.05 and abs(float(twin["c2st"]) - 0.5) < 0.15
    with pytest.raises(ValueError, match="must be unpaired"):
        JointEvaluator((50, 1), inputs=("theta",), paired=True, across_halves=4)


def test_split_half_scores_need_an_unpaired_evaluator(friction_draws):
    with pytest.raises(ValueError, match="must be unpaired"):
        split_half_scores(JointEvaluator((50, 1), inputs=("theta",), paired=True), friction_draws, tests=False)


def test_paired_energy_is_zero_for_identical_samples_and_unbiased_for_paired_draws(generator):
    """Paired rows (same inputs): the cross mean skips i = j, so identical samples score exactly 0."""
    x = torch.randn(50, 4, generator=generator, dtype=torch.float64)
    assert float(batched_energy(x[None], x[None], paired=True)[0]) == pytest.approx(0.0, abs=1e-9)
    assert float(batched_energy(x[None], x[None])[0]) < -0.05, "the unpaired form is biased low for paired samples"
    shared = torch.randn(400, 30, 4, generator=generator)  # each pair shares its input, draws differ
    draws = [shared + 0.5 * torch.randn(400, 30, 4, generator=generator) for _ in range(2)]
    paired = torch.stack([batched_energy(a[None], b[None], paired=True)[0] for a, b in zip(draws[0], draws[1])])
    assert abs(float(paired.mean())) < 3 * float(paired.std()) / math.sqrt(len(paired))
