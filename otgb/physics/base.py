"""The physics layer: one abstraction for the incomplete model f_p and the DGP.

A :class:`PhysicsModel` is a vector field f(t, state, theta) observed on a fixed time grid
and integrated with torchdiffeq's fixed-step solvers. The data-generating process is the
same model with named :class:`Term` objects added to the field (``with_hidden_effect``):
DGP = f_p + sum of terms, each term carrying its own latent physics parameters theta'
(paper, Evaluation: f_c = f_q o f_p with latent theta').

Shapes: state (B, *state_shape), theta (B, P), observed trajectory (B, T, *obs_shape).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn
from torchdiffeq import odeint

from otgb.physics.priors import Prior

VectorField = Callable[[Tensor, Tensor], Tensor]


class SimulationDiverged(FloatingPointError):
    """A solve produced NaN or Inf."""


class Term(nn.Module):
    """A named additive term of a vector field with its own latent parameters.

    ``priors`` maps each parameter name to the prior it is drawn from, once per trajectory.
    ``forward(state, params, model)`` returns the term's contribution to d(state)/dt, with params
    of shape (B, len(priors)) in the order of ``priors``; ``model`` is the physics model the term
    is part of (spatial terms read its grid: ``dx``, ``boundary``).
    """

    def __init__(self, priors: dict[str, Prior]) -> None:
        super().__init__()
        self.priors = dict(priors)

    @property
    def n_params(self) -> int:
        return len(self.priors)

    def sample_params(self, n: int, generator: torch.Generator) -> Tensor:
        columns = [prior.sample(n, generator) for prior in self.priors.values()]
        return torch.stack(columns, dim=-1) if columns else torch.zeros(n, 0)

    def extra_repr(self) -> str:
        return ", ".join(f"{name}={prior!r}" for name, prior in self.priors.items())


class PhysicsModel(nn.Module):
    """A simulator: vector field, observation, priors and a batched fixed-step solve.

    Subclasses define ``state_shape``, ``obs_shape``, ``theta_names``, :meth:`field`
    (the known physics f_p), :meth:`observe`, :meth:`sample_theta` and
    :meth:`sample_initial_state`.

    Args:
        dt: time between two observations.
        n_obs: number of observed time points.
        include_initial: whether the observation at t = 0 is part of the trajectory
            (t = 0, dt, ..., (n_obs-1) dt) or not (t = dt, ..., n_obs dt).
        step_size: solver step; defaults to ``dt``. Must divide ``dt``.
        method: a torchdiffeq fixed-grid method ("rk4", "euler", "midpoint", ...).
        hidden_effect: terms added to f_p; empty for f_p itself.
    """

    state_shape: tuple[int, ...]
    obs_shape: tuple[int, ...]
    theta_names: tuple[str, ...]

    def __init__(
        self,
        dt: float,
        n_obs: int,
        include_initial: bool = True,
        step_size: float | None = None,
        method: str = "rk4",
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        super().__init__()
        if dt <= 0 or n_obs < 1:
            raise ValueError(f"{type(self).__name__}: need dt > 0 and n_obs >= 1, got dt={dt}, n_obs={n_obs}")
        self.dt, self.n_obs, self.include_initial = float(dt), int(n_obs), include_initial
        self.step_size = self._checked_step(step_size if step_size is not None else dt)
        self.method = method
        self.terms = nn.ModuleList(hidden_effect)

    # --- to be defined by each system -------------------------------------------------
    def field(self, state: Tensor, theta: Tensor) -> Tensor:
        """The known physics f_p(state, theta), shape of ``state``."""
        raise NotImplementedError

    def observe(self, state: Tensor) -> Tensor:
        """Observation of states (..., *state_shape) -> (..., *obs_shape)."""
        raise NotImplementedError

    def sample_theta(self, n: int, generator: torch.Generator) -> Tensor:
        raise NotImplementedError

    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        raise NotImplementedError

    # --- the learned correction's slot ------------------------------------------------
    @property
    def correction_shape(self) -> tuple[int, ...]:
        """Shape of the correction f_phi adds to d(state)/dt; the whole state by default."""
        return self.state_shape

    def add_correction(self, dstate: Tensor, correction: Tensor) -> Tensor:
        return dstate + correction

    # --- shared machinery -------------------------------------------------------------
    @property
    def theta_dim(self) -> int:
        return len(self.theta_names)

    @property
    def trajectory_shape(self) -> tuple[int, ...]:
        return (self.n_obs, *self.obs_shape)

    @property
    def effect_dim(self) -> int:
        return sum(term.n_params for term in self.terms)

    @property
    def is_stochastic(self) -> bool:
        """Whether some hidden-effect parameter is random, i.e. the map is one-to-many."""
        return any(not p.is_constant for term in self.terms for p in term.priors.values())

    def times(self, device: torch.device | None = None) -> Tensor:
        n = self.n_obs if self.include_initial else self.n_obs + 1
        return torch.arange(n, device=device, dtype=torch.float32) * self.dt

    def with_hidden_effect(self, terms: Sequence[Term], step_size: float | None = None) -> PhysicsModel:
        """A copy of this model with ``terms`` added to its field (and optionally a finer step)."""
        model = copy.deepcopy(self)
        model.terms = nn.ModuleList([*self.terms, *copy.deepcopy(list(terms))])
        if step_size is not None:
            model.step_size = model._checked_step(step_size)
        return model

    def _checked_step(self, step_size: float) -> float:
        """A solver step that is positive and divides the observation interval dt."""
        if not step_size > 0 or abs(self.dt / step_size - round(self.dt / step_size)) > 1e-6:
            raise ValueError(f"{type(self).__name__}: step_size={step_size} must be positive and divide dt={self.dt}")
        return float(step_size)

    def sample_effect_params(self, n: int, generator: torch.Generator) -> Tensor:
        """Latent parameters theta' of every term, (n, effect_dim), drawn once per trajectory."""
        parts = [term.sample_params(n, generator) for term in self.terms]
        return torch.cat(parts, dim=-1) if parts else torch.zeros(n, 0)

    def vector_field(self, state: Tensor, theta: Tensor, effect_params: Tensor | None = None) -> Tensor:
        """f_p(state, theta) + sum over terms of term(state, theta'_term)."""
        dstate = self.field(state, theta)
        offset = 0
        for term in self.terms:
            dstate = dstate + term(state, effect_params[:, offset : offset + term.n_params], self)
            offset += term.n_params
        return dstate

    def solve(self, rhs: VectorField, initial_state: Tensor) -> Tensor:
        """Integrate d(state)/dt = rhs(t, state) on this model's grid: (B, T, *state_shape)."""
        t = self.times(initial_state.device)
        states = odeint(rhs, initial_state, t, method=self.method, options={"step_size": self.step_size})
        states = states.movedim(0, 1)
        return states if self.include_initial else states[:, 1:]

    def simulate(self, initial_state: Tensor, theta: Tensor, effect_params: Tensor | None = None) -> Tensor:
        """Observed trajectories (B, T, *obs_shape) of the full model (f_p plus its terms)."""
        self.check_inputs(initial_state, theta, effect_params)
        states = self.solve(lambda t, s: self.vector_field(s, theta, effect_params), initial_state)
        trajectories = self.observe(states)
        raise_if_diverged(trajectories, type(self).__name__, theta)
        return trajectories

    def check_inputs(self, initial_state: Tensor, theta: Tensor, effect_params: Tensor | None) -> None:
        name = type(self).__name__
        batch = initial_state.shape[0]
        if tuple(initial_state.shape[1:]) != tuple(self.state_shape):
            raise ValueError(
                f"{name}.simulate: initial state has shape {tuple(initial_state.shape)}, "
                f"expected (B, {', '.join(map(str, self.state_shape))})"
            )
        if tuple(theta.shape) != (batch, self.theta_dim):
            raise ValueError(
                f"{name}.simulate: theta has shape {tuple(theta.shape)}, "
                f"expected ({batch}, {self.theta_dim}) for {self.theta_names}"
            )
        needed = self.effect_dim
        if needed and (effect_params is None or tuple(effect_params.shape) != (batch, needed)):
            got = None if effect_params is None else tuple(effect_params.shape)
            raise ValueError(f"{name}.simulate: hidden-effect parameters have shape {got}, expected ({batch}, {needed})")


def raise_if_diverged(trajectories: Tensor, where: str, theta: Tensor) -> None:
    """Raise :class:`SimulationDiverged` naming the first bad trajectory if any value is NaN/Inf."""
    finite = torch.isfinite(trajectories.flatten(1)).all(dim=1)
    if bool(finite.all()):
        return
    bad = (~finite).nonzero().flatten()
    first = int(bad[0])
    raise SimulationDiverged(
        f"{where}: the solve produced NaN/Inf in {bad.numel()} of {len(finite)} trajectories "
        f"(first: index {first}, theta={theta[first].tolist()}); reduce the step size or check the parameters"
    )


def uniform_box(low: Sequence[float], high: Sequence[float], n: int, generator: torch.Generator) -> Tensor:
    """(n, len(low)) samples of independent uniforms on [low_i, high_i]."""
    low_t, high_t = torch.tensor(low, dtype=torch.float32), torch.tensor(high, dtype=torch.float32)
    return low_t + (high_t - low_t) * torch.rand(n, len(low), generator=generator)


def check_range(name: str, bounds: Sequence[float]) -> tuple[float, float]:
    """Validate a (low, high) pair from a config."""
    if len(bounds) != 2 or not (math.isfinite(bounds[0]) and math.isfinite(bounds[1])) or bounds[0] > bounds[1]:
        raise ValueError(f"{name} must be a finite (low, high) pair with low <= high, got {list(bounds)}")
    return float(bounds[0]), float(bounds[1])
