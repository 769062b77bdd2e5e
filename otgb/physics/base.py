"""The physics layer: one abstraction for the incomplete model f_p and the DGP.

A :class:`PhysicsModel` is a vector field f(t, state, theta) observed on a fixed time grid
and integrated with torchdiffeq's fixed-step solvers. A system declares the names of its
state components (``state_names``), which of them are observed (``observed``) and the names
of its parameters (``theta_names``); its constructor takes one :class:`Prior` per parameter
(and, for an ODE, per state component), from which theta and the initial state are drawn. A
system driven by inputs recorded beside its states names them in ``input_names``
(:mod:`otgb.physics.signals`).
:class:`FieldModel` is the base of fields on a uniform grid (PDEs by the method of lines).

The data-generating process is the same model with named :class:`Term` objects added to the
field (``with_hidden_effect``): DGP = f_p + sum of terms, each term carrying its own latent
physics parameters theta' (paper, Evaluation: f_c = f_q o f_p with latent theta').

Shapes: state (B, *state_shape), theta (B, P), observed trajectory (B, T, *obs_shape).
"""

from __future__ import annotations

import copy
import hashlib
import math
import numbers
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import ClassVar

import torch
from torch import Tensor, nn

from otgb.errors import InputError
from otgb.physics.arguments import RecordsInitArgs, invalid
from otgb.physics.priors import Prior, check_prior, sample_joint
from otgb.physics.reading import read_between_steps, steps_to_cover
from otgb.physics.signals import Recorded, SignalSource, check_signals, check_source, value_at
from otgb.physics.solvers import integrate
from otgb.physics.stencils import central_difference, laplacian, second_difference

VectorField = Callable[..., Tensor]  # field(state, *args) -> d(state)/dt

FIXED_STEP_METHODS = ("euler", "midpoint", "heun2", "heun3", "rk4", "explicit_adams", "implicit_adams", "fixed_adams")
BOUNDARIES = ("dirichlet", "periodic")
COORDINATE_NAMES = {1: ("s",), 2: ("x", "y")}  # a grid's axes in features, as in its derivatives d_s, d_x, d_y


def _check_declarations(cls: type[PhysicsModel]) -> None:
    """Validate a system's declared names once, when its class is created."""
    if getattr(cls, "state_names", None) is None:
        return  # an abstract base such as FieldModel
    if "observed" in cls.__dict__:
        cls._observed_by_default = False
    elif getattr(cls, "_observed_by_default", True):  # no class declared it: all of this class's states
        cls.observed, cls._observed_by_default = cls.state_names, True
    for attr in ("state_names", "observed", "theta_names", "input_names"):
        names = getattr(cls, attr, None)
        if names is None:
            raise TypeError(f"{cls.__name__} declares state_names but no {attr}")
        if isinstance(names, str) or not isinstance(names, (tuple, list)) or not all(isinstance(n, str) for n in names):
            raise TypeError(f"{cls.__name__}.{attr} must be a tuple of names (str), got {names!r}")
        if len(set(names)) != len(names):
            raise TypeError(f"{cls.__name__}.{attr} repeats a name: {tuple(names)}")
        setattr(cls, attr, tuple(names))
    if not cls.state_names or not cls.observed:
        raise TypeError(f"{cls.__name__}: state_names and observed need at least one name")
    unknown = [name for name in cls.observed if name not in cls.state_names]
    if unknown:
        raise TypeError(f"{cls.__name__}.observed names {unknown}, which are not in state_names {cls.state_names}")
    if list(cls.observed) != [name for name in cls.state_names if name in cls.observed]:
        raise TypeError(f"{cls.__name__}.observed {cls.observed} must follow the order of state_names {cls.state_names}")
    units = cls.units
    if not isinstance(units, dict) or not all(isinstance(k, str) and isinstance(v, str) and v for k, v in units.items()):
        raise TypeError(f"{cls.__name__}.units must map names (str) to units (non-empty str), got {units!r}")
    stray = [name for name in units if name not in ("t", *cls.state_names, *cls.theta_names, *cls.input_names)]
    if stray:
        raise TypeError(
            f"{cls.__name__}.units names {stray}, which are neither 't' nor in state_names, theta_names or input_names"
        )
    for attr in ("angle_names", "velocity_names"):
        stray = [name for name in getattr(cls, attr) if name not in cls.state_names]
        if stray:
            raise TypeError(f"{cls.__name__}.{attr} names {stray}, which are not in state_names {cls.state_names}")
    names = [*cls.theta_names, *cls.state_names, *cls.input_names]
    shared = sorted({name for name in names if names.count(name) > 1})
    if shared:
        raise TypeError(f"{cls.__name__}: {shared} named twice among theta_names, state_names and input_names")


def _is_number(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _is_integer(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


class SimulationDiverged(FloatingPointError):
    """A solve produced NaN or Inf."""


class PhysicsModel(RecordsInitArgs, nn.Module, ABC):
    """A simulator: vector field, observation, priors and a batched fixed-step solve.

    A subclass declares ``state_names``, ``observed`` (default: all of ``state_names``) and
    ``theta_names``, takes a :class:`Prior` argument named after each entry of ``theta_names``
    and ``state_names`` (or overrides :meth:`sample_theta` / :meth:`sample_initial_state`),
    and writes :meth:`field`, the known physics f_p. A system driven by recorded inputs declares their names in
    ``input_names``, takes an argument named after each (an input process such as
    :class:`otgb.physics.SumOfSines` that a generated DGP draws its signals from, or None) and writes
    ``field(state, theta, inputs)``, ``inputs`` (B, I) the inputs' values at the solve's time or None where it is
    not driven (zero inputs). Its constructor's arguments are recorded
    and make its ``repr``, the key of cached data sets. It may also name which states are
    angles (``angle_names``) and velocities (``velocity_names``): the missing-effect library
    (:mod:`otgb.discovery.library`) then offers sin/cos of the angles and drag-like terms of
    the velocities. Where the units are known, ``units`` maps the time ``"t"``, state and theta
    names to them (``{"t": "s", "angle": "rad"}``): figures label their axes with them.

    Args:
        dt: time between two observations.
        n_obs: number of observed time points.
        include_initial: whether the observation at t = 0 is part of the trajectory
            (t = 0, dt, ..., (n_obs-1) dt) or not (t = dt, ..., n_obs dt).
        step_size: solver step; defaults to ``dt``. Must divide ``dt``.
        method: a torchdiffeq fixed-grid method ("rk4", "euler", "midpoint", ...).
        hidden_effect: terms added to f_p; empty for f_p itself.
    """

    _measurement_noise: tuple[float, int] | None = None  # (sd, seed) while measured_with_noise is in force
    _first_row = 0  # the index of the observations' first trajectory in the set they are part of (rows_from)
    _read_times: Tensor | None = None  # the times it is observed at where they are not its own grid (read_at)
    _recorded: Recorded | None = None  # the recorded input signals its simulations draw (driven_by)

    state_names: ClassVar[tuple[str, ...]]
    observed: ClassVar[tuple[str, ...]]
    theta_names: ClassVar[tuple[str, ...]]
    input_names: ClassVar[tuple[str, ...]] = ()
    angle_names: ClassVar[tuple[str, ...]] = ()
    velocity_names: ClassVar[tuple[str, ...]] = ()
    units: ClassVar[dict[str, str]] = {}

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        _check_declarations(cls)

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
        if getattr(self, "state_names", None) is None or getattr(self, "theta_names", None) is None:
            raise TypeError(f"{type(self).__name__} must declare the class attributes state_names and theta_names")
        if not (_is_number(dt) and dt > 0):
            raise invalid(self, "dt", dt, "a positive number")
        if not (_is_integer(n_obs) and n_obs >= 1):
            raise invalid(self, "n_obs", n_obs, "an integer >= 1")
        if method not in FIXED_STEP_METHODS:
            raise invalid(self, "method", method, f"one of torchdiffeq's fixed-step methods {', '.join(FIXED_STEP_METHODS)}")
        self.dt, self.n_obs, self.include_initial = float(dt), int(n_obs), bool(include_initial)
        self.step_size = self._checked_step(step_size if step_size is not None else dt)
        self.method = method
        self.terms = nn.ModuleList(self._checked_terms(hidden_effect))
        self._check_priors()
        for name in self.input_names:
            check_source(self, name, self.init_args.get(name))

    # --- to be defined by each system -------------------------------------------------
    @abstractmethod
    def field(self, state: Tensor, theta: Tensor) -> Tensor:
        """The known physics f_p(state, theta), shape of ``state`` (a driven system's takes ``inputs`` too)."""

    # --- declared, with defaults --------------------------------------------------------
    @property
    def state_shape(self) -> tuple[int, ...]:
        """Shape of one state: (number of state components,) for an ODE."""
        return (len(self.state_names),)

    @property
    def obs_shape(self) -> tuple[int, ...]:
        """Shape of one observation: the observed components over the rest of the state's axes."""
        return (len(self.observed), *self.state_shape[1:])

    @property
    def priors(self) -> dict[str, Prior]:
        """The priors of theta and of the state components that the constructor took, by name."""
        return {name: self.init_args[name] for name in (*self.theta_names, *self.state_names) if name in self.init_args}

    def observe(self, state: Tensor) -> Tensor:
        """The ``observed`` components of states (..., *state_shape) -> (..., *obs_shape), plus the measurement noise
        while :meth:`measured_with_noise` is in force."""
        observed = self._observed_components(state)
        if self._measurement_noise is None:
            return observed
        sd, seed = self._measurement_noise
        generator = torch.Generator().manual_seed(seed + 1_000_003 * self._first_row)
        draw = torch.randn(observed.shape, generator=generator, dtype=torch.float64)
        return observed + sd * draw.to(observed)

    def _observed_components(self, state: Tensor) -> Tensor:
        if self.observed == self.state_names:
            return state
        axis = -len(self.state_shape)
        index = [self.state_names.index(name) for name in self.observed]
        if index == list(range(index[0], index[0] + len(index))):
            return state.narrow(axis, index[0], len(index))
        return state.index_select(axis, torch.tensor(index, device=state.device))

    @contextmanager
    def measured_with_noise(self, sd: float, seed: int) -> Iterator[None]:
        """Within it, every observation gets white Gaussian noise of standard deviation ``sd`` (the measurements'
        units), so that simulations compare with noisy measurements like for like. The noise of a shape is the same
        on every call (seeded by ``seed``): two models scored on the same inputs see the same noise (common random
        numbers), and a fit's loss stays a deterministic function of its coefficients. ``sd`` 0: no noise."""
        self._measurement_noise = (float(sd), int(seed)) if sd > 0 else None
        try:
            yield
        finally:
            self._measurement_noise = None

    @contextmanager
    def rows_from(self, first: int) -> Iterator[None]:
        """Within it, observed trajectories are rows ``first``, ``first + 1``, ... of a larger set simulated in chunks:
        their measurement noise is drawn for those rows, so that the chunks of a set do not repeat one another's."""
        previous, self._first_row = self._first_row, int(first)
        try:
            yield
        finally:
            self._first_row = previous

    def sample_theta(self, n: int, generator: torch.Generator) -> Tensor:
        """theta (n, P) from the priors named in ``theta_names`` (one joint uniform draw)."""
        return sample_joint([self.priors[name] for name in self.theta_names], n, generator)

    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        """Initial states (n, S) from the priors named in ``state_names`` (one joint uniform draw)."""
        return sample_joint([self.priors[name] for name in self.state_names], n, generator)

    # --- recorded inputs ----------------------------------------------------------------
    @property
    def is_driven(self) -> bool:
        """Whether its simulations have input signals: recorded ones (:meth:`driven_by`) or an input process's."""
        return self._recorded is not None or any(source is not None for source in self._processes())

    def _processes(self) -> list[SignalSource | None]:
        return [self.init_args.get(name) for name in self.input_names]

    def signal_times(self) -> Tensor:
        """The times (T_u,) its input signals are sampled at: the recorded ones, or its processes' grid to the end of
        the solve."""
        if self._recorded is not None:
            return self._recorded.times
        source = next(source for source in self._processes() if source is not None)
        return source.signal_times(float(self.observation_times()[-1]) + self.step_size, self.step_size)

    def sample_signals(self, n: int, generator: torch.Generator) -> Tensor | None:
        """Input signals (n, T_u, I) for n simulations: recorded rows, or new draws of each input's process (zero for
        an input without one); None where it is not driven. Drawn after x0 and theta, from the same generator."""
        if not self.is_driven:
            return None
        if self._recorded is not None:
            return self._recorded.sample(n, self._recorded.times, generator)
        times = self.signal_times()
        parts = [p.sample(n, times, generator) if p is not None else torch.zeros(n, len(times), 1) for p in self._processes()]
        return torch.cat(parts, dim=-1)

    def inputs_along(self, signals: Tensor) -> Tensor:
        """Input signals (B, T_u, I) read at the observation times: (B, T, I), the inputs beside each observed state."""
        times, signal_times = self.observation_times(signals.device), self.signal_times().to(signals.device)
        steps = len(times)
        rows = signals.repeat_interleave(steps, dim=0)
        return value_at(signal_times, rows, times.repeat(len(signals))).reshape(len(signals), steps, -1)

    def driven_by(self, recorded: Recorded) -> PhysicsModel:
        """A copy of this model whose simulations draw their input signals from ``recorded`` (a file's recorded inputs,
        :class:`otgb.physics.signals.Recorded`), in place of its input processes."""
        if not self.input_names:
            raise InputError(f"{type(self).__name__} has no recorded inputs (its input_names are empty)")
        model = copy.deepcopy(self)
        model._recorded = recorded
        return model

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
        """The solver's output grid from t = 0, (n_obs,) or (n_obs + 1,) when t = 0 is not observed."""
        n = self.n_obs if self.include_initial else self.n_obs + 1
        return torch.arange(n, device=device, dtype=torch.float32) * self.dt

    def observation_times(self, device: torch.device | None = None) -> Tensor:
        """The times of the observed trajectory, (n_obs,): its grid, or the times it is read at (:meth:`read_at`)."""
        if self._read_times is not None:
            return self._read_times.to(device=device, dtype=torch.float32)
        return self.times(device)[-self.n_obs :]

    def read_at(self, times: Tensor) -> PhysicsModel:
        """A copy of this model observed at ``times`` (T,) instead of its own grid (a file's own observation times,
        :mod:`otgb.data.times`): solved on its own step and read between steps at the solver's order
        (:mod:`otgb.physics.reading`). The times increase and lie in [0, this model's last observation time]."""
        times = torch.as_tensor(times, dtype=torch.float64).cpu()
        horizon = float(self.observation_times()[-1])
        if times.dim() != 1 or len(times) == 0 or bool((torch.diff(times) <= 0).any()):
            raise InputError(f"{type(self).__name__}.read_at: expected increasing times (T,), got shape {tuple(times.shape)}")
        if float(times[0]) < 0 or float(times[-1]) > horizon * (1 + 1e-6):
            raise InputError(
                f"{type(self).__name__}.read_at: times in [{float(times[0]):g}, {float(times[-1]):g}] leave [0, {horizon:g}]"
            )
        model = copy.deepcopy(self)
        model._read_times, model.n_obs = times, len(times)
        return model

    def __repr__(self) -> str:
        """The recorded constructor call, and the times the model is read at where they are not its grid."""
        text = super().__repr__()
        if self._read_times is None:
            return text
        digest = hashlib.sha256(self._read_times.numpy().tobytes()).hexdigest()[:12]
        times = self._read_times
        return f"{text}.read_at({len(times)} times in [{float(times[0]):g}, {float(times[-1]):g}], {digest})"

    def axis_label(self, name: str) -> str:
        """``name`` ("t", a state or theta name) with its unit where the model declares one: "angle (rad)"."""
        unit = self.units.get(name)
        return f"{name} ({unit})" if unit else name

    def with_hidden_effect(self, terms: Sequence[Term], step_size: float | None = None) -> PhysicsModel:
        """A copy of this model with ``terms`` added to its field (and optionally a finer step).

        The copy's recorded arguments (its repr) show the added terms and the step.
        """
        model = copy.deepcopy(self)
        model.terms = nn.ModuleList([*model.terms, *self._checked_terms(copy.deepcopy(list(terms)))])
        model.init_args = {**model.init_args, "hidden_effect": tuple(model.terms)}
        if step_size is not None:
            model.step_size = model._checked_step(step_size)
            model.init_args["step_size"] = model.step_size
        return model

    def with_priors(self, priors: dict[str, Prior]) -> PhysicsModel:
        """A copy of this model whose parameters or state components named in ``priors`` draw from those priors (a
        recalibrated model, :mod:`otgb.discovery.recalibration`); its recorded arguments show them."""
        unknown = sorted(set(priors) - {*self.theta_names, *self.state_names})
        if unknown:
            raise InputError(f"{type(self).__name__}.with_priors: {unknown} are not among its parameters or states")
        model = copy.deepcopy(self)
        model.init_args = {**model.init_args, **{name: check_prior(self, name, p) for name, p in priors.items()}}
        return model

    def _checked_step(self, step_size: float) -> float:
        """A solver step that is positive and divides the observation interval dt."""
        if not (_is_number(step_size) and step_size > 0) or abs(self.dt / step_size - round(self.dt / step_size)) > 1e-6:
            raise invalid(self, "step_size", step_size, f"a positive step that divides dt={self.dt}")
        return float(step_size)

    def _checked_terms(self, terms: Sequence[Term]) -> list[Term]:
        if isinstance(terms, (Term, str)) or not isinstance(terms, Sequence):
            raise invalid(self, "hidden_effect", terms, "a list of otgb.physics.Term objects")
        for i, term in enumerate(terms):
            if not isinstance(term, Term):
                raise invalid(self, f"hidden_effect[{i}]", term, "an otgb.physics.Term")
            term.check_model(self)
        return list(terms)

    def _check_priors(self) -> None:
        """The default samplers need a Prior argument named after each parameter / state component."""
        cls = type(self)
        needed = [*(cls.theta_names if cls.sample_theta is PhysicsModel.sample_theta else ())]
        needed += cls.state_names if cls.sample_initial_state is PhysicsModel.sample_initial_state else ()
        for name in needed:
            if name not in self.init_args:
                raise InputError(
                    f"{cls.__name__} draws {name!r} from its prior, but its constructor has no argument {name!r}; "
                    "add one (a Prior) or override sample_theta / sample_initial_state"
                )
        for name in (*self.theta_names, *self.state_names):
            if name in self.init_args:
                check_prior(self, name, self.init_args[name])

    def sample_effect_params(self, n: int, generator: torch.Generator) -> Tensor:
        """Latent parameters theta' of every term, (n, effect_dim), drawn once per trajectory."""
        parts = [term.sample_params(n, generator) for term in self.terms]
        return torch.cat(parts, dim=-1) if parts else torch.zeros(n, 0)

    def known_field(self, state: Tensor, theta: Tensor, inputs: Tensor | None = None) -> Tensor:
        """f_p(state, theta), with the inputs' values ``inputs`` (B, I) where the system is driven."""
        return self.field(state, theta, inputs) if self.input_names else self.field(state, theta)

    def vector_field(
        self, state: Tensor, theta: Tensor, effect_params: Tensor | None = None, inputs: Tensor | None = None
    ) -> Tensor:
        """f_p(state, theta) + sum over terms of term(state, theta'_term)."""
        dstate = self.known_field(state, theta, inputs)
        offset = 0
        for term in self.terms:
            params = effect_params[:, offset : offset + term.n_params]
            extra = {"inputs": inputs} if term.takes_inputs else {}
            dstate = dstate + term(state, params, self, theta, **extra)
            offset += term.n_params
        return dstate

    def solve(self, field: VectorField, initial_state: Tensor, *args: Tensor, signals: Tensor | None = None) -> Tensor:
        """Integrate d(state)/dt = field(state, *args) and read it at the observation times: (B, T, *state_shape).

        With input ``signals`` (B, T_u, I) at :meth:`signal_times`, ``field`` takes their values at the solve's time
        as the keyword ``inputs`` (B, I): the solve carries that time as one more state, the clock dt/dt = 1,
        which every Runge-Kutta method integrates exactly, so each stage reads the signals at its own time.
        The path (compiled, eager or torchdiffeq's) is :mod:`otgb.physics.solvers`'s setting.
        """
        if signals is None:
            return self._solve(field, initial_state, args)
        times = self.signal_times().to(initial_state.device)
        check_signals(f"{type(self).__name__}.solve", signals, len(initial_state), times, len(self.input_names))
        shape = initial_state.shape[1:]

        def clocked(y: Tensor, *arguments: Tensor) -> Tensor:
            *rest, values = arguments
            rate = field(y[:, :-1].unflatten(1, shape), *rest, inputs=value_at(times, values, y[:, -1]))
            return torch.cat([rate.flatten(1), torch.ones_like(y[:, -1:])], dim=1)

        clocked.eager_only = True
        start = torch.cat([initial_state.flatten(1), initial_state.new_zeros(len(initial_state), 1)], dim=1)
        states = self._solve(clocked, start, (*args, signals.to(initial_state)))
        return states[:, :, :-1].unflatten(2, shape)

    def _solve(self, field: VectorField, initial_state: Tensor, args: Sequence[Tensor]) -> Tensor:
        if self._read_times is not None:
            steps = steps_to_cover(self._read_times, self.step_size)
            states = integrate(field, initial_state, args, self.method, self.step_size, self.step_size, steps + 1)
            return read_between_steps(states, field, args, self.step_size, self._read_times)
        n_times = self.n_obs if self.include_initial else self.n_obs + 1
        states = integrate(field, initial_state, args, self.method, self.step_size, self.dt, n_times)
        return states if self.include_initial else states[:, 1:]

    def simulate(
        self, initial_state: Tensor, theta: Tensor, effect_params: Tensor | None = None, signals: Tensor | None = None
    ) -> Tensor:
        """Observed trajectories (B, T, *obs_shape) of the full model (f_p plus its terms), driven by ``signals``."""
        self.check_inputs(initial_state, theta, effect_params)
        states = self.solve(self.vector_field, initial_state, *self._field_args(theta, effect_params), signals=signals)
        trajectories = self.observe(states)
        raise_if_diverged(trajectories, type(self).__name__, theta)
        return trajectories

    def _field_args(self, theta: Tensor, effect_params: Tensor | None) -> tuple[Tensor, ...]:
        return (theta,) if effect_params is None else (theta, effect_params)

    def check_inputs(self, initial_state: Tensor, theta: Tensor, effect_params: Tensor | None) -> None:
        name = type(self).__name__
        batch = initial_state.shape[0]
        if tuple(initial_state.shape[1:]) != tuple(self.state_shape):
            raise InputError(
                f"{name}.simulate: initial state has shape {tuple(initial_state.shape)}, "
                f"expected (B, {', '.join(map(str, self.state_shape))})"
            )
        if tuple(theta.shape) != (batch, self.theta_dim):
            raise InputError(
                f"{name}.simulate: theta has shape {tuple(theta.shape)}, "
                f"expected ({batch}, {self.theta_dim}) for {self.theta_names}"
            )
        needed = self.effect_dim
        if needed and (effect_params is None or tuple(effect_params.shape) != (batch, needed)):
            got = None if effect_params is None else tuple(effect_params.shape)
            raise InputError(f"{name}.simulate: hidden-effect parameters have shape {got}, expected ({batch}, {needed})")


class FieldModel(PhysicsModel):
    """A field on a uniform grid (a PDE by the method of lines): state (channels, *grid_shape).

    The channels are the declared ``state_names``. Spatial terms (:class:`Advection`, ...) act
    only on a FieldModel and read its grid: :meth:`laplacian` and :meth:`derivative` apply the
    finite-difference stencils with its spacing and boundary. A field draws its initial state
    itself (a profile, a random field): :meth:`sample_initial_state` is abstract here.

    Args:
        grid_shape: points per spatial axis, at least 3 on each.
        dx: grid spacing, the same on every axis.
        boundary: "dirichlet" (the field is zero one step outside the grid) or "periodic".
        dt: time between two frames.
        n_obs: number of frames.
        include_initial: whether the frame at t = 0 is part of the trajectory.
        step_size: solver step; defaults to ``dt``. Must divide ``dt``.
        method: a torchdiffeq fixed-grid method ("rk4", "euler", "midpoint", ...).
        hidden_effect: terms added to f_p; empty for f_p itself.
    """

    def __init__(
        self,
        grid_shape: Sequence[int],
        dx: float,
        boundary: str,
        dt: float,
        n_obs: int,
        include_initial: bool = True,
        step_size: float | None = None,
        method: str = "rk4",
        hidden_effect: Sequence[Term] = (),
    ) -> None:
        if not (isinstance(grid_shape, Sequence) and len(grid_shape) > 0 and all(_is_integer(n) and n >= 3 for n in grid_shape)):
            raise invalid(self, "grid_shape", grid_shape, "one integer >= 3 per spatial axis")
        if not (_is_number(dx) and dx > 0):
            raise invalid(self, "dx", dx, "a positive number")
        if boundary not in BOUNDARIES:
            raise invalid(self, "boundary", boundary, f"one of {', '.join(map(repr, BOUNDARIES))}")
        # set before PhysicsModel.__init__, which checks the hidden-effect terms against the grid
        self.grid_shape, self.dx, self.boundary = tuple(int(n) for n in grid_shape), float(dx), boundary
        super().__init__(dt, n_obs, include_initial, step_size, method, hidden_effect)

    @property
    def state_shape(self) -> tuple[int, ...]:
        return (len(self.state_names), *self.grid_shape)

    @property
    def spatial_dims(self) -> int:
        return len(self.grid_shape)

    def laplacian(self, u: Tensor) -> Tensor:
        """The 3/5/...-point Laplacian over the trailing ``spatial_dims`` axes of u."""
        return laplacian(u, self.dx, self.boundary, dims=self.spatial_dims)

    def derivative(self, u: Tensor, axis: int = -1) -> Tensor:
        """du/ds along a spatial ``axis`` (negative) by central differences."""
        return central_difference(u, self.dx, self.boundary, axis)

    def second_derivative(self, u: Tensor, axis: int = -1) -> Tensor:
        """d^2u/ds^2 along a spatial ``axis`` (negative) by the 3-point stencil."""
        return second_difference(u, self.dx, self.boundary, axis)

    @property
    def coordinate_names(self) -> tuple[str, ...]:
        """The grid's coordinates as names in features (``s`` on a 1-D grid, ``x`` and ``y`` on a 2-D one, as in
        ``d_s(u)``, ``d_x(u)``), less any that a state or physics parameter of the model already uses."""
        taken = {*self.state_names, *self.theta_names}
        return tuple(name for name in COORDINATE_NAMES.get(self.spatial_dims, ()) if name not in taken)

    def coordinates(self, device: torch.device | None = None, dtype: torch.dtype = torch.float32) -> tuple[Tensor, ...]:
        """The position of every grid point along each axis, one tensor of ``grid_shape`` per axis: on a Dirichlet
        grid the points lie at dx, 2 dx, ..., n dx (the field is zero at 0 and (n + 1) dx), on a periodic one at
        0, dx, ..., (n - 1) dx. A model whose grid lies elsewhere overrides this."""
        first = 1 if self.boundary == "dirichlet" else 0
        axes = [torch.arange(first, n + first, device=device, dtype=dtype) * self.dx for n in self.grid_shape]
        return tuple(torch.meshgrid(*axes, indexing="ij"))

    def coordinate(self, name: str, device: torch.device | None = None, dtype: torch.dtype = torch.float32) -> Tensor:
        """The coordinate ``name`` (one of :attr:`coordinate_names`) of every grid point, of ``grid_shape``."""
        return self.coordinates(device, dtype)[COORDINATE_NAMES[self.spatial_dims].index(name)]

    @abstractmethod
    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        """Initial fields (n, *state_shape)."""


class Term(RecordsInitArgs, nn.Module, ABC):
    """A named additive term of a vector field with its own latent parameters.

    ``priors`` maps each parameter name to the prior it is drawn from, once per trajectory.
    ``forward(state, params, model, theta)`` returns the term's contribution to d(state)/dt, with
    params of shape (B, len(priors)) in the order of ``priors``; ``model`` is the physics model the
    term is part of and ``theta`` (B, P) its physics parameters (for effects whose strength
    depends on them). ``model_type`` is the kind of model the term needs (:class:`FieldModel` for
    spatial terms), checked by :meth:`check_model` when the term is added to a model.
    """

    model_type: ClassVar[type[PhysicsModel]] = PhysicsModel
    takes_inputs: ClassVar[bool] = False  # whether forward takes the keyword ``inputs``, a driven model's input values

    def __init__(self, priors: dict[str, Prior]) -> None:
        super().__init__()
        self.priors = {name: check_prior(self, name, prior) for name, prior in priors.items()}

    @abstractmethod
    def forward(self, state: Tensor, params: Tensor, model: PhysicsModel, theta: Tensor | None = None) -> Tensor:
        """d(state)/dt of this term for states (B, *state_shape) and its parameters (B, n_params)."""

    def check_model(self, model: PhysicsModel) -> None:
        """Raise InputError if this term cannot act on ``model``."""
        if not isinstance(model, self.model_type):
            raise InputError(
                f"{type(self).__name__} acts on an otgb.physics.{self.model_type.__name__}; {type(model).__name__} is not one"
            )

    @property
    def n_params(self) -> int:
        return len(self.priors)

    def sample_params(self, n: int, generator: torch.Generator) -> Tensor:
        columns = [prior.sample(n, generator) for prior in self.priors.values()]
        return torch.stack(columns, dim=-1) if columns else torch.zeros(n, 0)


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
