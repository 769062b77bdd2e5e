"""The paired check of f_p, where the measurements recorded each trajectory's inputs and their noise is given.

Solved on a measured trajectory's own initial state x0 and parameters theta, a complete f_p
would leave residuals y - f_p(x0, theta) that are the measurements' noise: white, Gaussian, of
the standard deviation sd given as ``data.measurement_noise``. The sum of the squared residuals
over sd^2 is then chi-square distributed with as many degrees of freedom as there are values; a
larger sum says that f_p misses the measurements by more than their noise. The locate step's
distribution tests cannot use the pairing, and need far more trajectories to see the same
effect. An sd set too small reads as a missing effect too: the check compares f_p with the
noise the user states.

Once terms with constant coefficients are named, the augmented physics is checked the same way
on the test part's recorded inputs, which no fit saw: residuals at the noise say the fix is
exact there; a larger RMS says the terms or their coefficients are not, even where the
distribution tests see no difference.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from scipy.stats import chi2
from torch import Tensor

from otgb.data.measured import simulate_in_chunks
from otgb.discovery.stages import stage
from otgb.physics.base import PhysicsModel


@dataclass(frozen=True)
class PairedCheck:
    """f_p on the recorded inputs: its residuals' RMS, the noise's sd, how many values, the chi-square p-value and
    whether it is significant at the level :func:`otgb.discovery.locate.locate` gives it."""

    rms: float
    noise: float
    values: int
    pvalue: float
    significant: bool = False
    model: str = "f_p"  # what was solved, as the sentence names it
    part: str = "the measurements'"  # whose recorded inputs, as the sentence names them
    diverged: int = 0  # trajectories whose solve left non-finite numbers (not in values, rms or the test)

    def to_dict(self) -> dict:
        return asdict(self)

    def sentence(self) -> str:
        p = f"= {self.pvalue:.2g}" if self.pvalue > 0 else "< 1e-300"
        test = f"(chi-square p {p} over {self.values} values)"
        if self.diverged and not self.values:
            return (
                f"{self.model} solved on {self.part} recorded inputs diverges on every trajectory ({self.diverged}): check "
                f"the recorded inputs, or what {self.model} lacks makes it unstable there"
            )
        if self.diverged:
            return (
                f"{self.model} solved on {self.part} recorded inputs diverges on {self.diverged} of their trajectories "
                f"(the others miss them by an RMS of {self.rms:.3g} against their noise's sd {self.noise:.3g}): check the "
                f"recorded inputs, or what {self.model} lacks makes it unstable there"
            )
        if self.significant:
            return (
                f"{self.model} solved on {self.part} recorded inputs misses them by an RMS of {self.rms:.3g}, more than "
                f"their noise's sd {self.noise:.3g} {test}"
            )
        return (
            f"{self.model} solved on {self.part} recorded inputs leaves residuals of RMS {self.rms:.3g}, consistent with their "
            f"noise's sd {self.noise:.3g} {test}"
        )


@torch.no_grad()
@stage("paired check")
def paired_check(
    physics: PhysicsModel, measured: Tensor, x0: Tensor, theta: Tensor, noise: float, signals: Tensor | None = None,
    **names: str,
) -> PairedCheck:  # fmt: skip
    """The check of the module docstring over the measured values: ``measured`` (n, T, *obs; NaN where missing), their
    inputs x0 (n, *state), theta (n, P) and recorded input signals (n, T_u, I; None: none); ``names``: the
    :class:`PairedCheck`'s ``model`` and ``part``, for its sentence."""
    simulated = simulate_in_chunks(physics, x0, theta, signals=signals).double().flatten(1)
    residuals = measured.double().flatten(1) - simulated
    finite = (torch.isfinite(simulated) & ~torch.isinf(residuals)).all(dim=1)
    kept = residuals[finite]
    kept = kept[~torch.isnan(kept)]  # a missing measured value (NaN) has no residual
    statistic = float(kept.pow(2).sum()) / noise**2
    pvalue = float(chi2.sf(statistic, kept.numel())) if bool(finite.all()) else 0.0  # a diverging solve is no noise
    rms = float(kept.pow(2).mean().sqrt()) if kept.numel() else float("nan")
    return PairedCheck(rms, noise, kept.numel(), pvalue, diverged=int((~finite).sum()), **names)
