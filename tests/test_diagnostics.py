"""scripts/one_to_many_diagnostics.py: what it measures on known cases, and a run through its command line."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).parents[1]
SCRIPT = ROOT / "scripts" / "one_to_many_diagnostics.py"


def _diagnostics():
    spec = importlib.util.spec_from_file_location("one_to_many_diagnostics", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_leading_direction_share_is_one_for_one_coefficient_and_lower_for_two(generator):
    share = _diagnostics().leading_direction_share
    base, first, second = torch.randn(3, 1, 50, 2, generator=generator).unbind(0)
    one = base + torch.rand(10, 1, 1, generator=generator) * first  # 10 draws of one input, one coefficient
    two = one + torch.rand(10, 1, 1, generator=generator) * second
    assert share(one[None]) == pytest.approx(1.0, abs=1e-9)
    assert share(two[None]) < 0.99
    assert share(torch.stack([one, two])) == pytest.approx((share(one[None]) + share(two[None])) / 2)


def test_leading_direction_alignment_tells_the_right_curve_from_another(generator):
    alignment = _diagnostics().leading_direction_alignment
    base, first, second = torch.randn(3, 1, 50, 2, generator=generator).unbind(0)
    along = lambda direction: base + torch.rand(10, 1, 1, generator=generator) * direction  # noqa: E731
    assert alignment(along(first)[None], along(-3 * first)[None]) == pytest.approx(1.0)
    other = second - (second * first).sum() / (first * first).sum() * first  # orthogonal to the first
    assert alignment(along(first)[None], along(other)[None]) == pytest.approx(0.0, abs=1e-6)


def test_the_complete_physics_draws_vary_along_one_curve(tmp_path):
    """Through the command line: the DGP's own simulator as the map matches the measured spread, on one curve."""
    xi = "{class_path: otgb.physics.Uniform, init_args: {low: 0.6, high: 1.5}}"
    hidden = f"[{{class_path: otgb.physics.ViscousFriction, init_args: {{xi: {xi}}}}}]"
    args = ["--config", str(ROOT / "configs" / "pendulum_mm.yaml"), "--no-per_frame", "--judges", "--data.n_test=16"]
    args += ["--data.draws_per_input=4", f"--data.cache_dir={tmp_path}"]
    args += ["--model.transport_map=otgb.models.CompletePhysicsMap"]
    done = subprocess.run([sys.executable, str(SCRIPT), *args, f"--model.transport_map.init_args.hidden_effect={hidden}"],
                          capture_output=True, text=True, cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    lines = {line.split(":")[0]: line.split(":")[-1] for line in done.stdout.splitlines() if ":" in line}
    shares = lines["variance share along each input's leading direction (whole trajectories)"]
    measured, drawn = (float(part.split()[-1]) for part in shares.split(","))
    assert measured > 0.95 and drawn > 0.95, "one random friction per trajectory: draws near one curve"
    assert float(lines["spread map / measured, mean over frames"]) == pytest.approx(1.0, abs=0.35)
    assert float(lines["|cos| between the map's and the measured leading directions"]) > 0.9
