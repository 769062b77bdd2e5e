"""Known-answer tests of the evaluation metrics (ABS ERR, N-RMSE, MMD, MMDAgg, C2ST, joint evaluation)."""

import logging
import math

import numpy as np
import pytest
import torch
from logcapture import records_of
from sklearn.neural_network import MLPClassifier

from otgb.data import generate_joint
from otgb.metrics import C2ST, MMD, NRMSE, AbsErr, MMDAgg, abs_err, c2st, energy, fused_judge, joint_samples, mmd2, mmdagg, nrmse
from otgb.metrics.c2st import make_classifier
from otgb.metrics.classifiers import PRECISIONS, PaperConvClassifier, PaperConvNet, few_channel_conv
from otgb.metrics.classifiers import MLPClassifier as TorchMLP
from otgb.metrics.joint import JointEvaluator, reference_scores
from otgb.metrics.mmd import PAPER_MULTIPLIERS, mmd_median, mmd_multiscale, standardise
from otgb.metrics.mmdagg import _memberships, _permuted_mmd2
from otgb.physics import Constant, Pendulum, Uniform, ViscousFriction


def test_errors_by_hand():
    pred = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    target = torch.tensor([[1.0, 2.0, 5.0], [1.0, -1.0, 1.0]])
    assert torch.allclose(abs_err(pred, target), torch.tensor([2 / 3, 1.0]))
    assert torch.allclose(nrmse(pred, target), torch.tensor([(4 / 3) ** 0.5 / 6, 1 / 6]))  # range 5 - (-1)


def test_error_metrics_accumulate_with_the_global_range(generator):
    pred, target = torch.randn(50, 7, generator=generator), torch.randn(50, 7, generator=generator)
    metric_abs, metric_nrmse = AbsErr(), NRMSE()
    for chunk in range(0, 50, 16):  # the range differs per batch; the metric uses the whole set's
        metric_abs.update(pred[chunk : chunk + 16], target[chunk : chunk + 16])
        metric_nrmse.update(pred[chunk : chunk + 16], target[chunk : chunk + 16])
    expected = nrmse(pred, target)
    out = metric_nrmse.compute()
    assert torch.isclose(out["nrmse"], expected.mean()) and torch.isclose(out["nrmse_std"], expected.std(), rtol=1e-5)
    assert torch.isclose(metric_abs.compute()["abs_err"], abs_err(pred, target).mean())
    with pytest.raises(ValueError, match="expected equal shapes"):
        metric_abs.update(pred, target[:, :3])


def _direct_mmd2(p, q, sq_bandwidth, unbiased):
    """MMD^2 by explicit double loops over all pairs."""
    k = lambda a, b: math.exp(-float(((a - b) ** 2).sum()) / sq_bandwidth)  # noqa: E731
    n, m = len(p), len(q)
    skip = 1 if unbiased else 0
    kpp = sum(k(p[i], p[j]) for i in range(n) for j in range(n) if not (unbiased and i == j)) / (n * (n - skip))
    kqq = sum(k(q[i], q[j]) for i in range(m) for j in range(m) if not (unbiased and i == j)) / (m * (m - skip))
    kpq = sum(k(p[i], q[j]) for i in range(n) for j in range(m)) / (n * m)
    return kpp + kqq - 2 * kpq


@pytest.mark.parametrize("unbiased", [True, False])
def test_mmd_equals_a_direct_computation(generator, unbiased):
    p, q = torch.randn(9, 3, generator=generator).double(), torch.randn(7, 3, generator=generator).double() + 0.3
    bandwidths = torch.tensor([0.5, 2.0], dtype=torch.float64)
    chunked = mmd2(p, q, bandwidths, unbiased=unbiased, chunk=4)  # several row blocks
    direct = [_direct_mmd2(p, q, float(b), unbiased) for b in bandwidths]
    assert torch.allclose(chunked, torch.tensor(direct, dtype=torch.float64), atol=1e-12)


def test_paper_code_mmd_is_the_biased_sum_of_six_kernels(generator):
    p, q = torch.randn(8, 2, generator=generator).double(), torch.randn(8, 2, generator=generator).double()
    zp, zq = standardise(p, q)
    pooled = torch.cat([zp, zq])
    h = float(torch.pdist(pooled).pow(2).mean())
    direct = sum(_direct_mmd2(zp, zq, h * mult, unbiased=False) for mult in PAPER_MULTIPLIERS)
    assert math.isclose(float(mmd_multiscale(p, q)), direct, rel_tol=1e-10)


def test_mmd_of_equal_distributions_is_within_permutation_noise_of_zero(generator):
    p, q = torch.randn(300, 4, generator=generator), torch.randn(300, 4, generator=generator)
    zp, zq = standardise(p, q)
    pooled = torch.cat([zp, zq])
    sigma2 = float(torch.pdist(pooled).median()) ** 2
    null = _permuted_mmd2(
        pooled, _memberships(300, 300, 200, 0, p.device, paired=False).float(), 300, torch.tensor([sigma2]), 256
    )
    observed = mmd_median(p, q)
    assert abs(float(observed)) < 3 * float(null[0, 1:].std())


def test_mmd_grows_with_the_shift(generator):
    p, q = torch.randn(400, 3, generator=generator), torch.randn(400, 3, generator=generator)
    shifts = [0.0, 0.25, 0.5, 1.0, 2.0]
    paper = [float(mmd_multiscale(p, q + s)) for s in shifts]
    median = [float(mmd_median(p, q + s)) for s in shifts]
    assert paper == sorted(paper) and median == sorted(median)
    assert median[-1] > 100 * abs(median[0])


def test_mmd_metric_accumulates_batches(generator):
    p, q = torch.randn(60, 3, generator=generator), torch.randn(60, 3, generator=generator) + 0.4
    metric = MMD(chunk=16)
    metric.update(p[:25], q[:25])
    metric.update(p[25:], q[25:])
    out = metric.compute()
    assert torch.isclose(out["mmd"], mmd_multiscale(p.double(), q.double()).float())
    assert torch.isclose(out["mmd2_median"], mmd_median(p.double(), q.double()).float())
    with pytest.raises(ValueError, match=r"sample q contains Inf \(NaN: a missing value\)"):
        metric.update(p, torch.full_like(q, float("inf")))


def test_a_missing_value_is_zero_in_both_samples_of_a_whole_row_score(generator):
    p, q = torch.randn(40, 4, generator=generator), torch.randn(40, 4, generator=generator) + 0.3
    gaps = torch.rand(40, 4, generator=generator) < 0.2
    gappy, filled = MMD(), MMD()
    gappy.update(p.masked_fill(gaps, float("nan")), q.masked_fill(gaps, float("nan")))
    filled.update(p.masked_fill(gaps, 0.0), q.masked_fill(gaps, 0.0))
    assert torch.isfinite(gappy.compute()["mmd"])
    assert torch.equal(gappy.compute()["mmd"], filled.compute()["mmd"])


@pytest.mark.parametrize("paired", [False, True])
def test_mmdagg_keeps_its_level_and_has_power(paired):
    g = torch.Generator().manual_seed(1)
    options = dict(n_permutations=500, n_level=500, paired=paired)
    rejections_null, rejections_alt = 0, 0
    for seed in range(60):
        inputs = torch.randn(40, 2, generator=g)  # paired rows share their inputs, like joint samples do
        p = torch.cat([inputs, torch.randn(40, 3, generator=g)], dim=1)
        q = torch.cat([inputs, torch.randn(40, 3, generator=g)], dim=1)
        rejections_null += int(mmdagg(p, q, seed=seed, **options)["mmdagg_reject"])
        if seed < 20:
            q_alt = q + torch.tensor([0.0, 0.0, 1.5, 0.0, 0.0])
            rejections_alt += int(mmdagg(p, q_alt, seed=seed, **options)["mmdagg_reject"])
    # level 0.05 + 3 binomial standard errors over 60 null draws
    assert rejections_null / 60 <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / 60)
    assert rejections_alt >= 19


@pytest.mark.parametrize("paired", [True, False])
def test_mmdagg_does_not_reject_bit_identical_samples(generator, paired):
    """p_agg = 1: every paired swap of identical samples leaves MMD^2_u unchanged (ties, which
    count), and every plain permutation can only raise it (the observed split keeps each
    point's twin in the other sample). In float32, or without the tie tolerance, about half
    the paired ties came out just below the observed value (p_agg < 1, down to a rejection)."""
    p = torch.randn(200, 6, generator=generator)
    out = mmdagg(p, p.clone(), paired=paired)
    assert out["mmdagg_reject"] == 0.0 and out["mmdagg_pvalue"] > 0.99


def test_reference_of_a_deterministic_dgp_is_not_rejected():
    """One-to-one pendulum with a constant friction: the Reference compares two bit-identical draw sets."""
    physics = Pendulum()
    dgp = physics.with_hidden_effect([ViscousFriction(Constant(1.2))])
    data = generate_joint(physics, dgp, 200, 1, 0, "val")
    assert torch.equal(data["y"], data["y_ref"])
    reference = reference_scores(JointEvaluator(tuple(data["y"].shape[2:])), data, tests=True, repeats=2)
    assert reference["mmdagg_reject"] == 0.0 and reference["mmdagg_pvalue"] > 0.5


def test_mmdagg_metric_and_bad_settings(generator):
    p, q = torch.randn(50, 2, generator=generator), torch.randn(50, 2, generator=generator) + 2.0
    metric = MMDAgg(n_permutations=200, n_level=50)
    metric.update(p, q)
    out = metric.compute()
    assert out["mmdagg_reject"] == 1.0 and out["mmdagg_pvalue"] <= 0.05 and out["mmdagg_mmd2"] > 0.1
    with pytest.raises(ValueError, match="alpha"):
        mmdagg(p, q, alpha=1.5)
    with pytest.raises(ValueError, match="cannot resolve level 0.05 over 5 bandwidths"):
        mmdagg(p, q, n_permutations=100)
    with pytest.raises(ValueError, match="paired samples need equal sizes"):
        mmdagg(p, q[:40], paired=True)


def test_c2st_is_chance_for_equal_and_one_for_separated_samples(generator):
    p, q = torch.randn(500, 4, generator=generator), torch.randn(500, 4, generator=generator)
    same = c2st(p, q)["c2st"]
    assert abs(float(same) - 0.5) <= 3 * 0.5 / math.sqrt(1000)
    assert c2st(p, q + 4.0)["c2st"] > 0.97
    with pytest.raises(ValueError, match="expected one of"):
        c2st(p, q, classifier="forest")
    q[3, 1] = float("nan")
    with pytest.raises(ValueError, match="MLPClassifier: the features contain NaN/Inf"):
        c2st(p, q)


def test_torch_mlp_judges_like_scikit_learns(generator):
    """Gaussians shifted by 1.5 along one axis: the Bayes classifier's accuracy is Phi(0.75) = 0.773.
    The "mlp" C2ST (torch, in float32 and in bfloat16 mixed precision) and scikit-learn's
    MLPClassifier with the same settings all come close to it from below and agree within noise;
    the torch one also trains under inference mode."""
    n, dim = 1000, 4
    p = torch.randn(n, dim, generator=generator)
    q = torch.randn(n, dim, generator=generator) + torch.tensor([1.5, 0.0, 0.0, 0.0])
    bayes, se = 0.5 * (1 + math.erf(0.75 / math.sqrt(2))), 0.5 / math.sqrt(2 * n)
    sklearn_mlp = MLPClassifier(hidden_layer_sizes=(10 * dim, 10 * dim), early_stopping=True, max_iter=1000, random_state=0)
    reference = float(c2st(p, q, classifier=sklearn_mlp)["c2st"])
    assert bayes - 6 * se <= reference <= bayes + 3 * se
    for precision in PRECISIONS[1:]:
        with torch.inference_mode():  # as inside Lightning's validation loop
            ours = float(c2st(p, q, classifier="mlp", precision=precision)["c2st"])
        assert bayes - 6 * se <= ours <= bayes + 3 * se and abs(ours - reference) <= 4 * se, precision


def test_torch_mlp_reports_its_training_like_scikit_learn(generator):
    features = torch.randn(1000, 3, generator=generator)
    labels = (features[:, 0] > 0).long()
    classifier = TorchMLP(n_iter_no_change=3).fit(features.numpy(), labels.numpy())
    assert classifier.n_iter_ == len(classifier.validation_scores_) >= 4
    assert classifier.best_validation_score_ == max(classifier.validation_scores_) > 0.7
    assert classifier.score(features.numpy(), labels.numpy()) > 0.8


def test_auto_precision_uses_bfloat16_only_where_it_is_native(generator, monkeypatch):
    classifier = TorchMLP(precision="auto")
    for native in (False, True):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda native=native: native)
        monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
        with classifier.autocast(torch.device("cpu")):
            assert torch.is_autocast_enabled("cpu") == native
    p = torch.randn(20, 2, generator=generator)
    with pytest.raises(ValueError, match="precision='16-mixed', expected one of"):
        c2st(p, p + 1, folds=2, precision="16-mixed")


def test_c2st_groups_rows_by_shared_inputs(generator):
    """Both classes hold rows for the same inputs; ungrouped folds push the accuracy below 0.5."""
    n, draws = 150, 4
    theta, x0 = torch.rand(n, 1, generator=generator), torch.rand(n, 2, generator=generator)
    base = torch.randn(n, 1, 20, 1, generator=generator)
    y = base + 0.3 * torch.randn(n, draws, 20, 1, generator=generator)
    y_other = base + 0.3 * torch.randn(n, draws, 20, 1, generator=generator)
    p, q = joint_samples(theta, x0, y), joint_samples(theta, x0, y_other)
    grouped = float(c2st(p, q, trajectory_shape=(20, 1))["c2st"])
    assert abs(grouped - 0.5) <= 3 * 0.5 / math.sqrt(2 * n * draws)


def test_conv_classifier_separates_fields(generator):
    """The conv C2ST on (theta, trajectory (T, C, X)) rows: a shifted field is found, equal fields are not."""
    n, shape = 200, (6, 2, 8)
    theta = torch.rand(n, 1, generator=generator)
    fields = torch.randn(n, 1, *shape, generator=generator)
    other = torch.randn(n, 1, *shape, generator=generator)
    p = joint_samples(theta, theta, fields)[:, 1:]  # inputs = theta only
    shifted = joint_samples(theta, theta, other + 0.5)[:, 1:]
    assert c2st(p, shifted, classifier="conv", trajectory_shape=shape)["c2st"] > 0.9
    with torch.inference_mode():  # as inside Lightning's validation loop
        assert c2st(p, shifted, classifier="conv", trajectory_shape=shape, folds=2)["c2st"] > 0.9
    metric = C2ST(classifier="conv", trajectory_shape=shape, folds=3)
    metric.update(p, joint_samples(theta, theta, other)[:, 1:])
    assert abs(float(metric.compute()["c2st"]) - 0.5) <= 3 * 0.5 / math.sqrt(2 * n)


def test_paper_judge_finds_a_shifted_field_and_not_an_equal_one(generator):
    """The paper's judge network (``"paper"``, three 3-filter convolutions along the whole row): a shift is found,
    equal fields are not (smaller batches and fewer epochs than its defaults, so that it trains in seconds)."""
    n, shape = 200, (8, 1, 6)
    theta = torch.rand(n, 1, generator=generator)
    fields = [torch.randn(n, 1, *shape, generator=generator) + shift for shift in (0, 0, 1)]
    p, same, shifted = (joint_samples(theta, theta, y)[:, 1:] for y in fields)
    judge = PaperConvClassifier(batch_size=32, max_epochs=100)
    assert c2st(p, shifted, classifier=judge, folds=2)["c2st"] > 0.9
    assert abs(float(c2st(p, same, classifier=judge, folds=2)["c2st"]) - 0.5) <= 1.5 / math.sqrt(2 * n)
    assert isinstance(make_classifier("paper", 49, None, seed=0), PaperConvClassifier), "selectable by name"


def test_the_paper_judge_stops_on_rows_it_separates_where_the_papers_tolerance_says(generator):
    """Separated rows' held-out log loss falls for ever as the logits grow: without a tolerance the judge trains to its
    last epoch; with the paper's 1e-4 it stops on its own, as accurate."""
    n, features = 100, 30

    def rows_and_labels():
        p = torch.randn(n, features, generator=generator)
        q = torch.randn(n, features, generator=generator) + 2 * torch.sin(torch.arange(features) / 3.0)
        return torch.cat([p, q]).numpy(), np.r_[np.zeros(n), np.ones(n)].astype(np.int64)

    (rows, labels), (fresh, truth) = rows_and_labels(), rows_and_labels()
    untolerant = PaperConvClassifier(batch_size=32, max_epochs=200, tol=0.0).fit(rows, labels)
    judge = PaperConvClassifier(batch_size=32, max_epochs=200).fit(rows, labels)
    assert judge.tol == 1e-4 and untolerant.n_iter_ == 200 and judge.n_iter_ < 200
    accuracy = [(classifier.predict(fresh) == truth).mean() for classifier in (judge, untolerant)]
    assert accuracy[0] >= accuracy[1] - 0.01 and accuracy[0] > 0.98, accuracy


def test_the_paper_judges_convolution_is_the_library_convolution_forward_and_backward(generator):
    torch.manual_seed(0)  # the layer's initial weights
    for channels_in in (1, 3):
        conv = torch.nn.Conv1d(channels_in, 3, 3, padding=1)
        x = torch.randn(16, channels_in, 41, generator=generator, requires_grad=True)
        fast, library = few_channel_conv(x, conv), conv(x)
        torch.testing.assert_close(fast, library, rtol=1e-5, atol=1e-6)
        weights = torch.randn_like(library)
        grads = [torch.autograd.grad((out * weights).sum(), (x, conv.weight, conv.bias)) for out in (fast, library)]
        for fast_grad, library_grad in zip(*grads):  # a weight's gradient sums 16 x 41 products of size ~1: a float32
            torch.testing.assert_close(fast_grad, library_grad, rtol=1e-4, atol=1e-4)  # sum that cancels is off by ~1e-5


@pytest.mark.skipif(bool(fused_judge.UNAVAILABLE), reason="numba does not import here")
@pytest.mark.parametrize("rows, features", [(1, 3), (2, 4), (37, 7), (37, 41), (37, 1041)])
def test_the_paper_judges_fused_loops_are_its_torch_network_forward_and_backward(generator, rows, features):
    """The CPU's fused loops and the network on torch's operations: the same logits and parameter gradients (float32),
    also where pooling by 3 leaves the row's last features out and where pre-activations are exactly 0 (LeakyReLU's
    slope, as torch's backward)."""
    net = PaperConvNet(features)
    x, weights = torch.randn(rows, features, generator=generator), torch.randn(rows, generator=generator)
    x[0, : features // 2] = 0
    for net_ in (net, _zero_first_layer(PaperConvNet(features))):
        fused, torch_ops = net_(x), net_.torch_forward(x)
        assert "Fused" in type(fused.grad_fn).__name__, "the fused loops ran"
        torch.testing.assert_close(fused, torch_ops, rtol=1e-5, atol=1e-6)
        grads = [torch.autograd.grad((logits * weights).sum(), list(net_.parameters())) for logits in (fused, torch_ops)]
        for fused_grad, torch_grad in zip(*grads):
            torch.testing.assert_close(fused_grad, torch_grad, rtol=1e-4, atol=1e-6)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        in_bfloat16 = net(x)
    assert "Fused" not in type(in_bfloat16.grad_fn).__name__, "bfloat16 runs on torch's operations"
    assert "Fused" not in type(net(x.clone().requires_grad_()).grad_fn).__name__, "a gradient of the rows: torch's"
    assert "Fused" not in type(net.double()(x.double()).grad_fn).__name__, "float64: torch's"


@pytest.mark.skipif(bool(fused_judge.UNAVAILABLE), reason="numba does not import here")
@pytest.mark.parametrize("features", [7, 41, 1041])
def test_a_fused_training_step_gives_the_log_loss_gradients_of_the_batchs_rows(generator, features):
    """One pass over the batch's rows, read in place: the gradients autograd gives for the mean binary cross-entropy of
    the network's logits of rows[batch] (torch's operations), including rows whose pre-activations are 0."""
    net = PaperConvNet(features)
    x, y = torch.randn(50, features, generator=generator), (torch.rand(50, generator=generator) < 0.5).float()
    x[3, : features // 2] = 0
    batch = torch.randperm(50, generator=generator)[:20]
    params = tuple(net.parameters())
    fused_judge.set_log_loss_gradients(x, y, batch, params)
    fused = [p.grad for p in params]
    loss = torch.nn.functional.binary_cross_entropy_with_logits(net.torch_forward(x[batch]), y[batch])
    for fused_grad, torch_grad in zip(fused, torch.autograd.grad(loss, params)):
        torch.testing.assert_close(fused_grad, torch_grad, rtol=1e-4, atol=1e-6)


def _zero_first_layer(net: PaperConvNet) -> PaperConvNet:
    with torch.no_grad():
        net[0].weight.zero_()
        net[0].bias.zero_()
    return net


@pytest.mark.skipif(bool(fused_judge.UNAVAILABLE), reason="numba does not import here")
def test_a_paper_judge_fit_on_the_fused_loops_is_its_fit_on_torchs_operations(generator, monkeypatch):
    """precision "auto" on a CPU trains on the fused loops, epoch by epoch as on torch's operations in float32."""
    p, q = torch.randn(80, 30, generator=generator), torch.randn(80, 30, generator=generator) * 1.2 + 0.3
    rows, labels = torch.cat([p, q]).numpy(), np.r_[np.zeros(80), np.ones(80)].astype(np.int64)
    calls = []
    step = fused_judge.set_log_loss_gradients
    monkeypatch.setattr(fused_judge, "set_log_loss_gradients", lambda *a: calls.append(1) or step(*a))
    fused = PaperConvClassifier(batch_size=32, max_epochs=30).fit(rows, labels)
    assert len(calls) == 30 * 5, "one pass per batch (144 training rows in 5 batches of <= 32) for 30 epochs"
    monkeypatch.setattr(PaperConvNet, "forward", PaperConvNet.torch_forward)
    torch_ops = PaperConvClassifier(batch_size=32, max_epochs=30, precision="32-true").fit(rows, labels)
    assert fused.n_iter_ == torch_ops.n_iter_
    np.testing.assert_allclose(fused.validation_scores_, torch_ops.validation_scores_, rtol=1e-4, atol=1e-6)


def test_the_paper_judge_without_numba_trains_on_torch_after_one_line(generator, monkeypatch):
    monkeypatch.setitem(fused_judge._state, "why", "numba did not import (ModuleNotFoundError: No module named 'numba')")
    monkeypatch.setitem(fused_judge._state, "said", False)
    rows = torch.cat([torch.randn(60, 20, generator=generator), torch.randn(60, 20, generator=generator) + 1]).numpy()
    labels = np.r_[np.zeros(60), np.ones(60)].astype(np.int64)
    with records_of("otgb.metrics", level=logging.WARNING) as records:
        judge = PaperConvClassifier(max_epochs=3, precision="32-true").fit(rows, labels)
        judge.predict(rows)
    lines = [record.getMessage() for record in records]
    assert len(lines) == 1 and "numba did not import (ModuleNotFoundError" in lines[0], lines
    assert judge.n_iter_ == 3


def test_auto_precision_of_the_paper_judge_is_float32_only_where_its_loops_compiled(monkeypatch):
    """On a CPU that multiplies bfloat16 natively, "auto" is float32 for the fused loops, and bfloat16 (as for the
    other judges) where they did not compile."""
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True)
    monkeypatch.setattr(fused_judge, "usable", lambda: True)
    with PaperConvClassifier(precision="auto").autocast(torch.device("cpu")):
        assert not torch.is_autocast_enabled("cpu")
    monkeypatch.setattr(fused_judge, "usable", lambda: False)
    with PaperConvClassifier(precision="auto").autocast(torch.device("cpu")):
        assert torch.is_autocast_enabled("cpu")


def test_c2st_permutation_pvalue(generator):
    p, q = torch.randn(100, 2, generator=generator), torch.randn(100, 2, generator=generator) + 3.0
    out = c2st(p, q, folds=3, n_permutations=5, classifier="mlp")
    assert out["c2st_pvalue"] == pytest.approx(1 / 6)


@pytest.mark.parametrize("classifier", ["mlp", PaperConvClassifier(max_epochs=20)], ids=["mlp", "paper"])
def test_c2st_folds_in_threads_give_what_they_give_in_turn(generator, classifier):
    """Each fold's network is seeded from torch's global generator: folds in threads must not draw from it at once."""
    p, q = torch.randn(150, 12, generator=generator), torch.randn(150, 12, generator=generator) * 1.3
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one thread per fold in both runs: the same arithmetic
    try:
        runs = [c2st(p, q, folds=4, classifier=classifier, n_jobs=jobs, n_permutations=2) for jobs in (1, 4)]
    finally:
        torch.set_num_threads(threads)
    assert runs[0] == runs[1]
    assert torch.get_num_threads() == threads, "the folds give torch its threads back"
    with pytest.raises(ValueError, match="n_jobs=-1, expected None"):
        c2st(p, q, classifier=classifier, n_jobs=-1)


@pytest.fixture(scope="module")
def one_to_many_set(tmp_path_factory):
    physics = Pendulum()
    dgp = physics.with_hidden_effect([ViscousFriction(Uniform(0.6, 1.5))])
    return generate_joint(physics, dgp, n=120, draws=4, seed=3, split="test")


def test_joint_evaluation_sees_a_wrong_conditional(one_to_many_set):
    """Draws with the right marginal of y but given to the wrong inputs must score badly."""
    data = one_to_many_set
    evaluator = JointEvaluator((50, 1), mmdagg_permutations=200)
    right = evaluator.evaluate(data["y_ref"], data, tests=True)  # independent DGP draws for the right inputs
    shuffled = data["y_ref"][torch.randperm(len(data["y_ref"]), generator=torch.Generator().manual_seed(0))]
    wrong = evaluator.evaluate(shuffled, data, tests=True)  # same draws, theta/x0 shuffled away from them
    noise = 3 * 0.5 / math.sqrt(2 * 120 * 4)
    assert abs(float(right["c2st"]) - 0.5) <= noise and right["mmdagg_reject"] == 0.0
    assert wrong["c2st"] > 0.5 + 2 * noise and wrong["mmdagg_reject"] == 1.0
    assert wrong["mmd"] > 3 * right["mmd"] and wrong["mmdagg_pvalue"] <= 0.05 < right["mmdagg_pvalue"]


def test_reference_scores_are_the_noise_floor(one_to_many_set):
    data = one_to_many_set
    evaluator = JointEvaluator((50, 1), mmdagg_permutations=200)
    reference = reference_scores(evaluator, data, tests=False, repeats=3)
    names = ("mmd", "mmd2_median", "energy", "energy_per_time")
    assert set(reference) == {f"{name}{std}" for name in names for std in ("", "_std")}
    fp = evaluator.evaluate(data["x"].unsqueeze(1).expand_as(data["y"]), data, tests=False)
    assert 0 < reference["mmd_std"] and reference["mmd"] < fp["mmd"] / 10
    one_draw = {**data, "y": data["y"][:, :1], "y_ref": data["y"][:, :1]}  # a deterministic DGP: both draws equal
    exact = reference_scores(evaluator, one_draw, tests=True, repeats=2)
    assert exact["abs_err"] == 0 and exact["nrmse"] == 0 and exact["c2st"] == 0.5


def test_draws_as_measured_move_the_two_sample_metrics_and_leave_the_pointwise_errors(one_to_many_set):
    """With the measurements' noise on the compared draws, the distances change; ABS ERR / N-RMSE stay the draws' own."""
    data = {**one_to_many_set, "y": one_to_many_set["y"][:, :1]}
    draws = data["x"].unsqueeze(1)
    noisy = draws + 0.5 * torch.randn(draws.shape, generator=torch.Generator().manual_seed(0))
    evaluator = JointEvaluator((50, 1), inputs=("theta", "x0"), paired=True)
    clean, measured = evaluator.evaluate(draws, data, tests=False), evaluator.evaluate(draws, data, False, as_measured=noisy)
    assert measured["abs_err"] == clean["abs_err"] and measured["nrmse"] == clean["nrmse"]
    assert measured["energy"] != clean["energy"] and measured["mmd"] != clean["mmd"]


def test_large_energy_distances_are_compiled_with_the_library_s_values_and_gradients(monkeypatch):
    """Distance matrices from COMPILED_ENTRIES entries on run compiled: the same means and gradients as cdist's."""
    torch.manual_seed(0)
    a, b = torch.randn(3, 40, 5, requires_grad=True), torch.randn(3, 30, 5)

    def means_and_gradient() -> list[torch.Tensor]:
        within, cross = energy.within_means(a), energy.cross_row_means(a, b)
        return [within, cross, *torch.autograd.grad(within.sum() + cross.square().sum(), a)]

    eager = means_and_gradient()
    monkeypatch.setattr(energy, "COMPILED_ENTRIES", 1)
    compiled = means_and_gradient()
    assert energy._compiled.cache_info().currsize >= 2, "both distance reductions were compiled"
    for x, y in zip(eager, compiled):
        assert torch.allclose(x, y, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("compiled", [False, True])
def test_cell_and_whole_distances_from_one_product_are_the_cells_and_the_whole_rows_apart(monkeypatch, compiled):
    """Values and gradients as the separate reductions of the cells and of the rows flattened, over blocks of rows,
    with a repeated row (a zero distance: a finite gradient) in the within-sample means."""
    torch.manual_seed(0)
    a = torch.randn(3, 9, 4)
    a = torch.cat([a, a[:, :1]], 1).requires_grad_()  # row 9 repeats row 0
    b = torch.randn(3, 6, 4)
    flat = lambda x: x.transpose(0, 1).flatten(1)[None]  # noqa: E731 -- (G, n, F) -> (1, n, G * F): the whole rows

    def apart() -> list[torch.Tensor]:
        cells, whole = energy.cross_row_means(a, b), energy.cross_row_means(flat(a), flat(b))[0]
        within_cells, within_whole = energy.within_means(a), energy.within_means(flat(a))[0]
        return [cells, whole, within_cells, within_whole]

    def together() -> list[torch.Tensor]:
        return [*energy.cell_and_whole_row_means(a, b), *energy.cell_and_whole_within_means(a)]

    def with_gradient(means: list[torch.Tensor]) -> list[torch.Tensor]:
        return [*means, *torch.autograd.grad(sum(m.square().sum() for m in means), a)]

    expected = with_gradient(apart())
    monkeypatch.setattr(energy, "MAX_BLOCK_ENTRIES", 3 * 6 * 4)  # blocks of 4 rows
    monkeypatch.setattr(energy, "COMPILED_ENTRIES", 1 if compiled else 10**9)
    for x, y in zip(expected, with_gradient(together())):
        assert torch.isfinite(y).all() and torch.allclose(x, y, rtol=1e-5, atol=1e-5), (x, y)


def test_energy_distances_that_cannot_be_compiled_run_eagerly_after_one_line(monkeypatch):
    def cannot_compile(function):
        def fail(*samples):
            raise RuntimeError("no C compiler\nsecond line")

        return fail

    torch.manual_seed(0)
    a, b = torch.randn(2, 20, 3), torch.randn(2, 10, 3)
    expected = energy.cross_row_means(a, b)
    monkeypatch.setattr(energy, "COMPILED_ENTRIES", 1)
    monkeypatch.setattr(energy, "compile_generic", cannot_compile)
    monkeypatch.setattr(energy, "_not_compilable", set())
    energy._compiled.cache_clear()
    try:
        with records_of("otgb.metrics", level=logging.WARNING) as records:
            assert torch.equal(energy.cross_row_means(a, b), expected)
            assert torch.equal(energy.cross_row_means(a, b), expected)
    finally:
        energy._compiled.cache_clear()  # the next test compiles for real
    assert [r.getMessage() for r in records] == [
        "otgb: energy distances run eagerly: they could not be compiled (RuntimeError: no C compiler)"
    ]
