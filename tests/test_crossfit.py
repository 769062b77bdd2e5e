"""Cross-fitted held-out scores (otgb.discovery.crossfit): the folds, how fold scores combine, the standard error of a
difference, and a real fit on a pendulum."""

import math

import pytest
import torch

from otgb.data import generate_measured
from otgb.discovery.crossfit import Folds, cross_fitted, refit_steps
from otgb.discovery.library import Candidate
from otgb.discovery.refine import CoefficientPrior, Fitting, fit, refit_on
from otgb.discovery.scores import Scores, difference, fold_inflation
from otgb.discovery.settings import DiscoverySettings
from otgb.errors import InputError
from otgb.physics import Pendulum
from otgb.physics.priors import Constant
from otgb.physics.terms import LibraryTerm


def test_folds_partition_the_pooled_training_and_validation_trajectories_the_same_way_for_one_seed():
    train, val = torch.arange(17.0)[:, None], 100 + torch.arange(6.0)[:, None]
    folds = Folds.of(train, val, 4, seed=3)
    rows = torch.cat(folds.index)
    assert folds.k == 4 and sorted(rows.tolist()) == list(range(23)), "each trajectory in exactly one fold"
    assert {len(i) for i in folds.index} <= {5, 6}
    rest, fold = folds.split(1)
    assert len(rest) + len(fold) == 23 and not set(rest[:, 0].tolist()) & set(fold[:, 0].tolist())
    assert all(torch.equal(a, b) for a, b in zip(folds.index, Folds.of(train, val, 4, seed=3).index))
    assert Folds.of(train, val, 1, seed=3) is None
    with pytest.raises(InputError, match="discover.folds=12: the 23 measured training and validation trajectories cannot"):
        Folds.of(train, val, 12, seed=3)


def test_fold_scores_combine_by_fold_size_per_draw_and_keep_each_trajectory_row_from_the_fold_that_held_it_out():
    folds = Folds.of(torch.zeros(6, 1), torch.zeros(3, 1), 3, seed=0)
    per_fold = {}

    def score_fold(k, rest, fold):
        per_fold[k] = Scores([float(k), 10.0 + k], torch.full((len(fold),), float(k), dtype=torch.float64))
        return per_fold[k]

    combined = cross_fitted(folds, score_fold)
    assert combined.folds == 3 and combined.draws == pytest.approx([1.0, 11.0])  # equal folds of 3: the mean
    assert combined.rows.tolist() == [0.0] * 3 + [1.0] * 3 + [2.0] * 3
    diverged = cross_fitted(folds, lambda k, rest, fold: Scores([0.0, 0.0]) if k else Scores.diverged(2))
    assert not diverged.finite and diverged.folds == 3


def test_the_measured_part_of_a_cross_fitted_difference_is_scaled_by_nadeau_and_bengios_correction():
    rows_a, rows_b = torch.tensor([0.0, 1.0, 2.0, 3.0]), torch.tensor([0.5, 1.0, 3.0, 3.5])
    draws = [1.0, 1.0, 1.0]  # no simulation noise: the measured part alone
    single = difference(Scores(draws, rows_a), Scores([2.0] * 3, rows_b))
    five = difference(Scores(draws, rows_a, 5), Scores([2.0] * 3, rows_b, 5))
    by_hand = float((rows_b - rows_a).var() / 4) ** 0.5
    assert single == pytest.approx((1.0, by_hand)) and five == pytest.approx((1.0, by_hand * math.sqrt(2.25)))
    assert fold_inflation(1) == 1.0 and fold_inflation(5) == 2.25 and fold_inflation(2) == 3.0
    with pytest.raises(ValueError, match="scores of 1 and 5 folds are not comparable"):
        difference(Scores(draws, rows_a), Scores(draws, rows_b, 5))


def test_a_cross_fitted_fit_keeps_the_training_parts_coefficients_and_scores_every_pooled_trajectory_out_of_sample():
    pendulum = Pendulum()
    dgp = pendulum.with_hidden_effect([LibraryTerm("velocity", "velocity", Constant(-0.8))])
    train, val = generate_measured(dgp, 60, 1)["y"], generate_measured(dgp, 20, 2)["y"]
    friction = [Candidate("velocity", "velocity")]
    single = Fitting(pendulum, train, val, 6, 32, 0)
    crossed = Fitting(pendulum, train, val, 6, 32, 0, folds=Folds.of(train, val, 4, 0))
    a, b = single(friction, [-0.5]), crossed(friction, [-0.5])
    assert [p.value for p in a.priors] == [p.value for p in b.priors], (
        "the answer's coefficients are its fit on the training part either way"
    )
    assert (len(a.heldout.rows), a.heldout.folds) == (20, 1) and (len(b.heldout.rows), b.heldout.folds) == (80, 4)
    alone = crossed.alone()
    assert alone.folds == 4 and len(alone.rows) == 80
    gain, error = difference(b.heldout, alone)
    assert gain > 2 * error > 0, "a friction of -0.8 is seen against f_p alone on 80 trajectories"
    assert crossed.evidence_on() == "the 80 training and validation trajectories, cross-fitted over 4 folds"
    assert single.evidence_on() is None


@pytest.mark.parametrize("folds", [0, 21, 2.5, True])
def test_a_bad_number_of_folds_is_refused_in_one_line(folds):
    with pytest.raises(InputError, match=rf"discover.folds={folds!r} is invalid; expected a whole number 1..20"):
        DiscoverySettings(folds=folds)


def test_a_fold_refit_from_the_training_parts_end_reaches_the_other_folds_own_optimum():
    """A fold's refit starts where the fit on the training part ended (which saw most of the fold) and takes a fifth of
    its iterations: two correlated frictions must end where a full fit on the other folds alone ends, not near the
    start (the start is 0.03 to 0.07 from that end), in fewer evaluations than that full fit."""
    pendulum = Pendulum()
    frictions = [
        LibraryTerm("velocity", "velocity", Constant(-0.5)),
        LibraryTerm("velocity*|velocity|", "velocity", Constant(-0.3)),
    ]
    dgp = pendulum.with_hidden_effect(frictions)
    train, val = generate_measured(dgp, 90, 1)["y"], generate_measured(dgp, 30, 2)["y"]
    fitting = Fitting(pendulum, train, val, 30, 96, 0, folds=Folds.of(train, val, 4, 0))
    terms = [Candidate("velocity", "velocity"), Candidate("velocity*|velocity|", "velocity")]
    on_train = fit(pendulum, terms, [-0.3, -0.1], "constant", train, val, 30, 96, 0, score=False)
    assert refit_steps(30) == 6
    for k in (0, 2):
        rest, fold = fitting.folds.split(k)
        own = fit(pendulum, terms, [-0.3, -0.1], "constant", rest, fold, 30, 96, 0, score=False)
        refit = refit_on(pendulum, on_train, rest, fold, fitting)
        assert refit.heldout.finite and len(refit.heldout.rows) == len(fold) and len(refit.loss) < len(own.loss)
        for got, start, target in zip(refit.centres, on_train.centres, own.centres):
            assert abs(got - target) < 0.2 * abs(start - target) + 0.01, (k, got, start, target)


def test_a_refit_of_a_family_that_varies_starts_where_its_fit_ended_but_no_narrower_than_a_fit_from_scratch():
    """A width near zero barely moves (the softplus that keeps it positive is flat there)."""
    usual = CoefficientPrior("uniform", [-0.5]).width.tolist()
    ended = CoefficientPrior("uniform", [-0.5])
    ended.shift.data.fill_(0.2)
    ended.raw_width.data.fill_(-12.0)
    assert ended.widen_to_start().width.tolist() == pytest.approx(usual) and ended.centre.tolist() == pytest.approx([-0.4])
    ended.raw_width.data.fill_(1.0)
    assert ended.widen_to_start().width.tolist() == pytest.approx(ended.width.tolist()) and ended.raw_width.item() == 1.0


def test_a_candidate_without_a_natural_scale_moves_in_units_of_its_start():
    """The theta search's candidates (omega*velocity) have no natural scale from f_phi's design: fitted beside those
    that have one, they move in units of their start's size (a run stopped on a KeyError before)."""
    pendulum = Pendulum()
    train, val = generate_measured(pendulum, 30, 1)["y"], generate_measured(pendulum, 10, 2)["y"]
    friction, scaled = Candidate("velocity", "velocity"), Candidate("omega*velocity", "velocity")
    fitting = Fitting(pendulum, train, val, 2, 16, 0, natural={friction: 0.5})
    fitted = fitting([friction, scaled], [-0.1, 0.0])
    assert fitted.scales == [0.5, 0.0] and len(fitted.priors) == 2
