"""Fixed-step solves of d(state)/dt = field(state, *args): a fast path and torchdiffeq's, the reference.

Every simulator, grey-box map and discovery fit integrates its vector field on a fixed grid
with an explicit Runge-Kutta method (RK4 by default). torchdiffeq (``odeint``) does this with a
Python loop over hundreds of tiny tensor operations per solve, each paying the interpreter's
and the kernel launch's overhead: for the pendulum (2 states, batch 32) that overhead is most
of a training step. The fast path takes the same methods with the same formulas (torchdiffeq's
Butcher tableaus, RK4 as its 3/8 rule) and compiles them with ``torch.compile``, shape-generic
in the batch so that a partial last batch, validation and test sizes and every DDP process
reuse one graph. Two designs, chosen by the size of the state and the device (measured with
``scripts/speed_benchmark.py designs`` and ``steps``):

- a small state on the CPU (at most :data:`WHOLE_SOLVE_MAX_STATE` numbers per trajectory, an ODE
  such as the pendulum): the whole solve is one compiled loop (torch's ``scan``), forward and
  backward, so no Python or autograd bookkeeping runs between steps; for such states that
  bookkeeping is most of the time.
- a field (a PDE on a grid, the advection-diffusion rod included), and any state on a GPU: one
  whole Runge-Kutta step (its stages and the field they call) is one compiled graph, called once
  per step. On the CPU a field's convolutions are most of the time, and the compiled loop ran no
  faster than the step there. On a GPU the step is replayed as a CUDA graph, one launch for its
  kernels, while inductor runs a compiled ``scan`` as a loop on the host that waits for the GPU
  at every iteration (the ``pendulum-gpu`` rows of docs/results.md).

The path is one process-wide setting (``otgb fit --solver NAME``, :func:`set_solver`):

- ``auto`` (default): compiled once the vector field of one model (per grad mode) has been, or
  is planned to be, solved :data:`COMPILE_AFTER` times; the eager loop before. A compile is
  paid once per model (less from torch's on-disk compile cache) and pays for itself only over
  several hundred to a thousand solves on 2 cores (whole pendulum fits at 500, 1500 and 3000 steps,
  eager against compiled from an empty cache: ``scripts/speed_benchmark.py fit --cold-cache``,
  docs/results.md; the threshold keeps a margin above that), so short runs (tests, smoke runs) and discovery's many
  small fits, each of a new model, never compile, and a long training run, which announces
  its steps (:func:`plan_solves`), compiles at once.
  The switch is a count, not a clock: the same config and seed give the same numbers run
  after run (a resumed run may switch at another step: the paths agree to float32 rounding).
- ``compiled``: the compiled step from the first solve.
- ``eager``: the same Runge-Kutta loop, never compiled.
- ``torchdiffeq``: ``torchdiffeq.odeint``, the reference the fast path is tested against.

A field that cannot be compiled (data-dependent Python control flow, an unsupported platform,
no C compiler) runs eagerly, after one line on stderr saying why. The Adams methods are
torchdiffeq's only.
"""

from __future__ import annotations

import functools
import logging
import math
import weakref
from collections.abc import Callable, Sequence

import torch
from torch import Tensor
from torch._higher_order_ops.scan import scan
from torchdiffeq import odeint

from otgb.compiling import EagerFallback, compile_generic
from otgb.errors import InputError

SOLVERS = ("auto", "compiled", "eager", "torchdiffeq")
COMPILE_AFTER = 1500  # solves of one model's field (per grad mode) that `auto` runs eagerly before compiling them
WHOLE_SOLVE_MAX_STATE = 8  # numbers per trajectory's state up to which the whole solve is one compiled loop

Field = Callable[..., Tensor]
log = logging.getLogger("otgb.solvers")

_setting: dict[str, object] = {"solver": "auto", "planned": 0}
_solves: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # per field owner (a model): solves per (method, grad mode)
_not_compilable: set[tuple] = set()
_gradients_checked: set[tuple] = set()  # fields whose compiled gradients have been compared with the eager loop's
_announced: set[tuple] = set()  # fields whose compile has been announced (INFO of the ``otgb.solvers`` logger)
GRADIENT_TOLERANCE = 1e-3  # of the largest gradient: a compiled solve further from the eager loop's is not used


def set_solver(name: str) -> None:
    """Choose the solve path for this process: one of :data:`SOLVERS`."""
    _setting["solver"] = checked_solver(name)


def current_solver() -> str:
    return str(_setting["solver"])


def plan_solves(n: int) -> None:
    """Tell ``auto`` that every field will be solved about ``n`` more times (a training run's remaining steps; 0: unknown)."""
    _setting["planned"] = max(0, int(n)) if math.isfinite(n) else 0


def reset() -> None:
    """Back to the default path, with no solves counted and every field compilable again."""
    _setting.update(solver="auto", planned=0)
    _solves.clear()
    _not_compilable.clear()
    _gradients_checked.clear()
    _announced.clear()


def checked_solver(name: object, where: str = "solver") -> str:
    if name not in SOLVERS:
        raise InputError(f"{where}={name!r} is invalid; expected one of {', '.join(SOLVERS)}")
    return str(name)


# --- the Runge-Kutta steps: torchdiffeq's formulas, term for term ------------------------
def _euler(field: Field, y: Tensor, h: float, args: Sequence[Tensor]) -> Tensor:
    return y + h * field(y, *args)


def _midpoint(field: Field, y: Tensor, h: float, args: Sequence[Tensor]) -> Tensor:
    k1 = field(y, *args)
    return y + h * field(y + k1 * (0.5 * h), *args)


def _heun2(field: Field, y: Tensor, h: float, args: Sequence[Tensor]) -> Tensor:
    k1 = field(y, *args)
    k2 = field(y + h * k1 * 1.0, *args)
    return y + h * (k1 * 0.5 + k2 * 0.5)


def _heun3(field: Field, y: Tensor, h: float, args: Sequence[Tensor]) -> Tensor:
    k1 = field(y, *args)
    k2 = field(y + h * k1 * (1 / 3), *args)
    k3 = field(y + h * (k1 * 0.0 + k2 * (2 / 3)), *args)
    return y + h * (k1 * 0.25 + k2 * 0.0 + k3 * 0.75)


def _rk4(field: Field, y: Tensor, h: float, args: Sequence[Tensor]) -> Tensor:
    """The 3/8 rule, as torchdiffeq's "rk4"."""
    k1 = field(y, *args)
    k2 = field(y + h * k1 * (1 / 3), *args)
    k3 = field(y + h * (k2 - k1 * (1 / 3)), *args)
    k4 = field(y + h * (k1 - k2 + k3), *args)
    return y + (k1 + 3 * (k2 + k3) + k4) * h * 0.125


STEPS: dict[str, Callable[[Field, Tensor, float, Sequence[Tensor]], Tensor]] = {
    "euler": _euler,
    "midpoint": _midpoint,
    "heun2": _heun2,
    "heun3": _heun3,
    "rk4": _rk4,
}


def _compile(function: Callable, device_type: str) -> Callable:
    """``function`` compiled for tensors on ``device_type``, generic in the batch.

    On the CPU the graph's calling code is C++ (inductor's ``cpp_wrapper``) rather than Python:
    a solve is thousands of small kernels, and the Python that calls them, checks their inputs'
    sizes and allocates their outputs was a third of a compiled pendulum solve
    (``scripts/speed_benchmark.py designs``). On a GPU each call is replayed as a CUDA graph.
    """
    # every field, grad mode and dtype is one more graph of the same function; step sizes are constants of the graph
    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
    torch._dynamo.config.specialize_float = True
    return compile_generic(function, cpp_wrapper=device_type == "cpu", cuda_graphs=device_type == "cuda")


@functools.cache
def compiled_step(method: str, device_type: str) -> Callable:
    """The step of ``method`` compiled for ``device_type`` (the ``compiled`` solver's step on a GPU)."""
    return _compile(STEPS[method], device_type)


def whole_solve(
    field: Field, initial_state: Tensor, args: Sequence[Tensor], method: str, step_size: float, substeps: int, n_intervals: int
) -> Tensor:
    """States (B, n_intervals + 1, *state): ``substeps`` steps per interval, the loop over intervals as torch's ``scan``."""
    step = STEPS[method]

    def interval(state: Tensor, _: Tensor) -> tuple[Tensor, Tensor]:
        for _ in range(substeps):
            state = step(field, state, step_size, args)
        return state, state.clone()

    _, states = scan(interval, initial_state, initial_state.new_zeros(n_intervals, 1))
    return torch.cat([initial_state[:, None], states.movedim(0, 1)], dim=1)


@functools.cache
def compiled_whole_solve(device_type: str) -> Callable:
    """:func:`whole_solve` compiled for ``device_type`` (the ``compiled`` solver on a CPU)."""
    return _compile(whole_solve, device_type)


# --- the solve ---------------------------------------------------------------------------
def integrate(
    field: Field, initial_state: Tensor, args: Sequence[Tensor], method: str, step_size: float, dt: float, n_times: int
) -> Tensor:
    """States (B, n_times, *state) at t = 0, dt, ..., (n_times - 1) dt, from ``initial_state`` (B, *state).

    ``field(state, *args)`` is d(state)/dt; ``step_size`` divides ``dt``.
    """
    solver = current_solver()
    if solver == "torchdiffeq" or method not in STEPS:  # the Adams methods are torchdiffeq's only
        t = torch.arange(n_times, device=initial_state.device, dtype=torch.float32) * dt
        states = odeint(lambda _, s: field(s, *args), initial_state, t, method=method, options={"step_size": step_size})
        return states.movedim(0, 1)
    substeps = round(dt / step_size)
    if getattr(field, "eager_only", False):  # a field made for one solve (a driven model's clocked field): nothing to reuse
        return stepwise_solve(field, initial_state, args, method, step_size, substeps, n_times - 1)
    key = (method, getattr(field, "__func__", field), torch.is_grad_enabled())
    compiled = _compiles(solver, key, getattr(field, "__self__", field))
    arguments = (initial_state, args, method, step_size, substeps, n_times - 1)
    if not compiled:
        return stepwise_solve(field, *arguments)
    device = initial_state.device.type
    _announce_compile(key, field, solver)
    if device != "cuda" and initial_state[0].numel() <= WHOLE_SOLVE_MAX_STATE and n_times > 1:
        fast = functools.partial(_fallback(key, compiled_whole_solve(device), stepwise_solve), field)
    else:
        fast = functools.partial(stepwise_solve, field, step=_fallback(key, compiled_step(method, device), STEPS[method]))
    if torch.is_grad_enabled() and key not in _gradients_checked:
        _check_against_eager(key, field, fast, arguments)
        if key in _not_compilable:
            return stepwise_solve(field, *arguments)
    return fast(*arguments)


def stepwise_solve(
    field: Field,
    initial_state: Tensor,
    args: Sequence[Tensor],
    method: str,
    step_size: float,
    substeps: int,
    n_intervals: int,
    step: Callable | None = None,
) -> Tensor:
    """:func:`whole_solve` as a Python loop over ``step`` (default: the method's eager step)."""
    eager = STEPS[method]
    step = step or eager
    states, y = [initial_state], initial_state
    for i in range(n_intervals * substeps):
        # the first step of a differentiated solve starts from a state without a graph: eager, rather than one more compiled graph
        first = i == 0 and torch.is_grad_enabled() and not initial_state.requires_grad
        y = (eager if first else step)(field, y, step_size, args)
        if (i + 1) % substeps == 0:
            states.append(y)
    return torch.stack(states, dim=1)


def _check_against_eager(key: tuple, field: Field, fast: Callable[..., Tensor], arguments: tuple) -> None:
    """Compare the first differentiated compiled solve of a field with the eager loop's, by its gradients.

    A compiler can trace a solve right and differentiate it wrong: torch 2.11's compiled loop gave
    the grey-box's parameters gradients near zero on an H100 with the right trajectories, and
    training went on, far worse. So once per field and process, the gradients of a fixed
    projection of the states, with respect to the field's parameters and the solve's inputs, are
    compared; where they differ by more than :data:`GRADIENT_TOLERANCE` of their largest, the field
    runs eagerly from then on (``key`` joins the fields that do not compile), after one line saying so.
    The check runs on detached copies of the inputs, so the caller's graph is left as it was.
    """
    _gradients_checked.add(key)
    owner = getattr(field, "__self__", None)
    parameters = [p for p in owner.parameters() if p.requires_grad] if isinstance(owner, torch.nn.Module) else []
    initial_state, args = _leaf(arguments[0]), tuple(_leaf(a) for a in arguments[1])
    inputs = parameters + [t for t in (initial_state, *args) if isinstance(t, Tensor) and t.requires_grad]
    if not inputs:
        return
    copies = (initial_state, args, *arguments[2:])
    states = fast(*copies)
    if key in _not_compilable:
        return
    weights = torch.linspace(-1, 1, states[0].numel(), device=states.device, dtype=states.dtype).reshape(states.shape[1:])
    fast_gradients = (
        torch.autograd.grad((states * weights).sum(), inputs, allow_unused=True) if states.requires_grad else [None] * len(inputs)
    )
    eager_gradients = torch.autograd.grad((stepwise_solve(field, *copies) * weights).sum(), inputs, allow_unused=True)
    largest = max((float(g.abs().max()) for g in eager_gradients if g is not None), default=0.0)
    difference = max(_relative_difference(a, b, 1e-2 * largest) for a, b in zip(fast_gradients, eager_gradients))
    if difference > GRADIENT_TOLERANCE:
        _not_compilable.add(key)
        log.warning(
            f"otgb: the solve of {_field_name(field)} runs eagerly: its compiled gradients differ from the eager "
            f"loop's by {difference:.2g} of their largest (torch {torch.__version__}, {states.device.type})"
        )


def _leaf(value: object) -> object:
    """A tensor cut from its graph, still requiring a gradient where it did; anything else as it is."""
    return value.detach().requires_grad_(value.requires_grad) if isinstance(value, Tensor) else value


def _relative_difference(gradient: Tensor | None, reference: Tensor | None, floor: float) -> float:
    """|gradient - reference| at its largest, over the reference's largest (at least ``floor``); None is zero."""
    gradient = torch.zeros_like(reference) if gradient is None and reference is not None else gradient
    reference = torch.zeros_like(gradient) if reference is None and gradient is not None else reference
    if gradient is None:
        return 0.0
    scale = reference.abs().max().clamp_min(max(floor, 1e-12))
    return float((gradient - reference).abs().max() / scale)


def _compiles(solver: str, key: tuple, owner: object) -> bool:
    """Whether this solve of the field ``key`` (a method of ``owner``) runs compiled, counting it for ``auto``."""
    if solver == "eager" or key in _not_compilable:
        return False
    counts = _solves.setdefault(owner, {})
    counts[key] = counts.get(key, 0) + 1
    return solver != "auto" or counts[key] + int(_setting["planned"]) > COMPILE_AFTER


def _announce_compile(key: tuple, field: Field, solver: str) -> None:
    """One INFO line where a field's solve is compiled for the first time in this process: the compile holds a run up
    for a minute or more on a few cores (less from torch's on-disk compile cache)."""
    if key in _announced or key in _not_compilable:
        return
    _announced.add(key)
    why = f"(solver auto: {COMPILE_AFTER} solves of it run or planned)" if solver == "auto" else f"(solver {solver})"
    gradients = "and its gradients " if key[2] else ""
    log.info(
        f"otgb: compiling the solve of {_field_name(field)} {gradients}{why}: once a run, a minute or more on a few "
        "cores, less where torch's compile cache holds it"
    )


def _fallback(key: tuple, compiled: Callable, eager: Callable) -> EagerFallback:
    """The compiled solve (or step); if it cannot be compiled, its eager twin, with one line saying why."""
    return EagerFallback(key, compiled, eager, _not_compilable, _fallback_line, log)


def _fallback_line(field: Field, *arguments) -> str:
    return f"the solve of {_field_name(field)} runs eagerly: it could not be compiled"


def _field_name(field: Field) -> str:
    owner = getattr(field, "__self__", None)
    name = getattr(field, "__qualname__", repr(field))
    return f"{type(owner).__name__}.{field.__name__}" if owner is not None else name
