"""Parametric forms: one shape as a library feature with its parameters written in and as a FormTerm whose parameters
are drawn; a user's own form by class path; bad input named in one line; discovery weighing them against linear terms."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from otgb.data import generate_measured
from otgb.discovery.forms import form_step
from otgb.discovery.library import Candidate, term_name
from otgb.discovery.refine import Fitting
from otgb.discovery.regression import Design
from otgb.discovery.settings import DiscoverySettings
from otgb.errors import InputError
from otgb.physics import AdvectionDiffusion, Augmented, Constant, FormTerm, LibraryTerm, Pendulum
from otgb.physics.forms import BUILT_IN, Form, form_feature


class Arrhenius(Form):
    """A user's form: exp(-energy / (1 + u)), a rate that grows with a temperature-like state."""

    parameters, positive = ("energy",), ("energy",)

    def shape(self, inputs, values):
        return torch.exp(-values[0] / (1 + inputs[0].abs()))


USER_FORM = f"{__name__}.Arrhenius"
ROOT = Path(__file__).parents[1]


def _solve(model, x0, theta):
    return model.solve(model.vector_field, x0, theta)


@pytest.mark.parametrize(
    ("form", "values"),
    [("saturating", {"v0": 0.8}), ("rational", {"v0": 1.2}), ("stribeck", {"ratio": 0.5, "vs": 0.3}), ("power", {"p": 1.5}),
     ("exponential", {"rate": 0.4}), (USER_FORM, {"energy": 0.7})],
)  # fmt: skip
def test_a_form_written_into_a_feature_solves_as_the_form_term_with_those_parameters(form, values, generator):
    pendulum = Pendulum()
    feature = form_feature(form, ["velocity"], values)
    written = Augmented(pendulum, [LibraryTerm(feature, "velocity", Constant(-0.9))])
    drawn = Augmented(
        pendulum, [FormTerm(form, "velocity", ["velocity"], Constant(-0.9), {k: Constant(v) for k, v in values.items()})]
    )
    assert drawn.theta_names[1:] == (drawn.added[0].name, *(f"{drawn.added[0].name}__{k}" for k in values))
    x0, omega = pendulum.sample_initial_state(6, generator), pendulum.sample_theta(6, generator)
    a = _solve(written, x0, torch.cat([omega, torch.full((6, 1), -0.9)], 1))
    b = _solve(drawn, x0, drawn.sample_theta(6, torch.Generator().manual_seed(0)).index_copy(1, torch.tensor([0]), omega))
    assert torch.allclose(a, b, rtol=1e-5, atol=1e-5) and not torch.allclose(a, _solve(pendulum, x0, omega), atol=1e-3)


def test_each_built_in_shape_has_the_slope_or_level_of_the_linear_term_it_generalises():
    """Near rest a saturating friction is viscous (slope 1); far from it a power law with p = 2 is quadratic drag; a
    bump peaks at 1 at its centre."""
    v = torch.tensor([-1e-3, 1e-3])
    for name in ("saturating", "rational"):
        assert torch.allclose(BUILT_IN[name]().shape([v], [torch.tensor(0.5)]) / v, torch.ones(2), atol=1e-4)
    speeds = torch.tensor([-2.0, 3.0])
    assert torch.allclose(BUILT_IN["power"]().shape([speeds], [torch.tensor(2.0)]), speeds * speeds.abs())
    assert float(BUILT_IN["bump"]().shape([torch.tensor(0.3)], [torch.tensor(0.3), torch.tensor(0.1)])) == 1.0


def test_a_bump_fixed_in_space_adds_to_a_field_most_at_its_centre():
    rod = AdvectionDiffusion()
    heated = Augmented(rod, [LibraryTerm("bump(s; centre=0.5, width=0.1)", "T", Constant(2.0))])
    x0 = rod.sample_initial_state(2, torch.Generator().manual_seed(0))
    theta = rod.sample_theta(2, torch.Generator().manual_seed(1))
    added = heated.vector_field(x0, torch.cat([theta, torch.full((2, 1), 2.0)], 1)) - rod.vector_field(x0, theta)
    s = rod.coordinate("s", x0.device, x0.dtype)
    assert torch.allclose(added[:, 0], 2.0 * torch.exp(-((s - 0.5) ** 2) / (2 * 0.1**2)).expand(2, -1), atol=1e-5)


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: LibraryTerm("rational(velocity; w=0.8)", "velocity", Constant(-1.0)).check_model(Pendulum()),
         "the form 'rational' takes 1 variable(s) and the parameters ['v0'] written name=value in that order"),
        (lambda: LibraryTerm("rational(velocity; v0=fast)", "velocity", Constant(-1.0)).check_model(Pendulum()),
         "the parameters of 'rational' must be numbers"),
        (lambda: LibraryTerm("rational(speed; v0=1)", "velocity", Constant(-1.0)).check_model(Pendulum()),
         "'speed' is not a name of Pendulum"),
        (lambda: LibraryTerm("wobbly(velocity; v0=1)", "velocity", Constant(-1.0)).check_model(Pendulum()),
         "form 'wobbly' is unknown; expected one of ['bump', 'bump2', 'exponential', 'power'"),
        (lambda: FormTerm("stribeck", "velocity", ["velocity"], Constant(-1.0), {"ratio": Constant(1.0)}),
         "FormTerm: the form 'stribeck' takes 1 variable(s) and the parameters ['ratio', 'vs']"),
        (lambda: Augmented(Pendulum(), [FormTerm("power", "speed", ["velocity"], Constant(-1.0), {"p": Constant(1.0)})]),
         "FormTerm: ['speed'] are not names of Pendulum"),
        (lambda: DiscoverySettings(forms=[{"class_path": USER_FORM, "component": "velocity", "variables": ["velocity"]}]),
         "discover.forms[0]=['class_path', 'component', 'variables'] is invalid; expected the keys"),
        (lambda: DiscoverySettings(forms=[{"class_path": USER_FORM, "component": "velocity", "variables": ["velocity"],
                                           "ranges": {"energy": [0.0, 2.0]}}]),
         "low > 0 for ['energy']"),
        (lambda: DiscoverySettings(forms=[{"class_path": "my.Missing", "component": "u", "variables": ["u"], "ranges": {}}]),
         "form 'my.Missing' is unknown"),
    ],
)  # fmt: skip
def test_a_form_given_wrongly_is_refused_in_one_line_naming_what_was_expected(build, message):
    with pytest.raises(InputError) as error:
        build()
    assert message in str(error.value) and "\n" not in str(error.value), str(error.value)


def test_a_declared_form_is_kept_with_its_ranges_as_numbers():
    entry = {"class_path": USER_FORM, "component": "velocity", "variables": "velocity", "ranges": {"energy": [0.1, 3]}}
    (checked,) = DiscoverySettings(forms=[entry]).fits.forms
    assert checked["variables"] == ["velocity"] and checked["ranges"] == {"energy": (0.1, 3.0)}


def _linear_and_design(truth, kept_terms, init):
    """A pendulum whose friction is ``truth`` (a FormTerm or LibraryTerm), 1000 training and 250 validation
    trajectories, the linear ``kept_terms`` fitted to them, and f_phi's design as a well trained grey-box gives it
    (the missing rate along 200 trajectories)."""
    pendulum = Pendulum()
    dgp = pendulum.with_hidden_effect([truth])
    fitting = Fitting(pendulum, generate_measured(dgp, 1000, 21)["y"], generate_measured(dgp, 250, 22)["y"], 50, 512, 0)
    kept = fitting(kept_terms, init, natural_scales=False)
    with_truth = Augmented(pendulum, [truth])
    g = torch.Generator().manual_seed(3)
    states = with_truth.solve(with_truth.vector_field, with_truth.sample_initial_state(200, g), with_truth.sample_theta(200, g))
    theta = with_truth.sample_theta(1, torch.Generator().manual_seed(0))[:, 1:].expand(len(states.flatten(0, 1)), -1)
    rate = truth.rate(states.flatten(0, 1), theta, pendulum, None).double().numpy()
    v = states[..., 1].flatten().double().numpy()
    library = [Candidate("velocity", "velocity"), Candidate("sign(velocity)", "velocity")]
    design = Design(library, np.stack([v, np.sign(v)], 1), rate, np.repeat(np.arange(200), states.shape[1]))
    return fitting, kept, {"velocity": design}


def test_a_friction_that_saturates_is_named_as_a_saturating_friction_with_its_speed_and_intervals():
    """-v / (1 + (v / 1.5)^2), fitted by the linear library as viscous plus Coulomb friction: the forms are weighed
    (two linear terms share one effect), a saturating friction replaces both, its coefficient and speed within 20 %
    and inside their 95 % intervals."""
    truth = FormTerm("rational", "velocity", ["velocity"], Constant(-1.0), {"v0": Constant(1.5)})
    linear = [Candidate("velocity", "velocity"), Candidate("sign(velocity)", "velocity")]
    fitting, kept, designs = _linear_and_design(truth, linear, [-0.5, -0.3])
    step = form_step(kept, [], designs, fitting, [], remainder=lambda: pytest.fail("two terms share one effect"))
    assert step.reason == "two linear terms share one effect" and step.adopted is not None, [f.to_dict() for f in step.tried]
    adopted = step.adopted
    assert term_name(adopted.candidate, -1.0, Pendulum()).startswith("saturating friction"), adopted.candidate
    assert adopted.offer.form == "rational" and step.kept.candidates == [adopted.candidate]
    (c,), (v0,) = [p.value for p in adopted.fitted.priors], adopted.values.values()
    assert abs(c + 1.0) < 0.2 and abs(v0 - 1.5) < 0.3, (c, v0)
    assert adopted.coefficient_interval[0] < -1.0 < adopted.coefficient_interval[1], adopted.coefficient_interval
    assert adopted.intervals["v0"][0] < 1.5 < adopted.intervals["v0"][1], adopted.intervals
    assert "replaces viscous friction and Coulomb friction" in step.said(Pendulum())[0]


def test_a_viscous_friction_is_not_called_saturating():
    """Viscous friction alone, the forms weighed anyway (a remainder said): each has one parameter more than viscous
    friction and does not fit the validation part better by two standard errors, so none is adopted."""
    truth = LibraryTerm("velocity", "velocity", Constant(-0.8))
    fitting, kept, designs = _linear_and_design(truth, [Candidate("velocity", "velocity")], [-0.5])
    step = form_step(kept, [], designs, fitting, [], remainder=lambda: True)
    assert step.reason.startswith("the linear terms leave a remainder") and len(step.tried) == 4
    assert step.adopted is None and step.kept is kept, [f.to_dict() for f in step.tried]


def test_a_declared_form_of_ones_own_is_weighed_in_place_of_the_kept_terms_on_its_component():
    truth = LibraryTerm("velocity", "velocity", Constant(-0.8))
    fitting, kept, designs = _linear_and_design(truth, [Candidate("velocity", "velocity")], [-0.5])
    entry = {"class_path": USER_FORM, "component": "velocity", "variables": ["velocity"], "ranges": {"energy": [0.05, 5.0]}}
    declared = list(DiscoverySettings(forms=[entry]).fits.forms)
    step = form_step(kept, [], designs, fitting, declared, remainder=lambda: pytest.fail("declared forms are weighed"))
    assert step.reason == "forms were declared (discover.forms)" and len(step.tried) == 5
    (mine,) = [f for f in step.tried if f.offer.form == USER_FORM]
    assert mine.offer.covers == (Candidate("velocity", "velocity"),) and mine.candidate.feature.startswith(f"{USER_FORM}(")
    assert mine.refused is not None and step.adopted is None, mine.to_dict()  # a constant-like push is no friction


@pytest.mark.slow
def test_discover_names_a_saturating_friction_in_a_file_from_scipy_with_its_coefficient_and_speed(tmp_path):
    """README's discover command on 1000 trajectories from SciPy's solve_ivp with the friction -0.8 v / (1 + (v / 2)^2)
    (v0 about half the largest speed): a saturating friction named, c and v0 within 20 %, the gap closed."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from scipy_pendulum import write

    measured = write(tmp_path / "rational.csv", "rational", 0.8, 2.0, 0.0, 1000, 0, 0.02)
    args = ["discover", "--config", str(ROOT / "configs" / "pendulum.yaml"), "--data.hidden_effect=[]"]
    args += [f"--data.measured_path={measured}", "--data.measurement_noise=0.02", "--data.simulation_budget=32000"]
    args += [f"--data.cache_dir={tmp_path / 'cache'}", "--trainer.enable_progress_bar=false"]
    done = subprocess.run([sys.executable, "-m", "otgb.cli", *args], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    run_dir = Path(done.stdout.strip().splitlines()[-1].split("report in ")[1])
    report = json.loads((tmp_path / run_dir / "report.json").read_text())
    (term,) = report["terms"]
    assert term["name"].startswith("saturating friction") and report["outcome"] == "gap closed", report["verdict"]
    (v0,) = term["parameters"]
    assert abs(term["coefficient"] + 0.8) < 0.16 and abs(v0["value"] - 2.0) < 0.4, term
    assert "rational(velocity;v0=" in (tmp_path / run_dir / "augmented.yaml").read_text()
