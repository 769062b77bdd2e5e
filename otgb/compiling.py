"""``torch.compile`` as otgb uses it: one graph for every batch size, and the eager twin where compiling fails.

Two parts of otgb run compiled: the fixed-step solves (:mod:`otgb.physics.solvers`) and the
large energy-distance reductions (:mod:`otgb.metrics.energy`). Both compile with
:func:`compile_generic` and call through :class:`EagerFallback`, so that a platform without a C
compiler, or a user's function that cannot be traced whole, runs on the eager path after one
line saying why, never a crash.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Hashable

import torch

from otgb.errors import first_line


def compile_generic(function: Callable, cpp_wrapper: bool = False, cuda_graphs: bool = False) -> Callable:
    """``function`` under ``torch.compile``, whole (``fullgraph``) and generic in its sizes (``dynamic``).

    ``cpp_wrapper``: the graph's calling code is C++ rather than Python (inductor's option), for
    graphs of thousands of small kernels (a solve), where the Python that calls them, checks
    their inputs and allocates their outputs costs more than the kernels.
    ``cuda_graphs``: on a GPU, each call replays its kernels as one recorded CUDA graph
    (``mode="reduce-overhead"``), one launch instead of one per kernel. A replay writes its output
    where the last replay wrote it, so the result is copied out before it is returned.
    """
    _lower_view_copies()
    _quiet_value_range_analysis()
    if cuda_graphs:
        return _copied_out(torch.compile(function, mode="reduce-overhead", dynamic=True, fullgraph=True))
    return torch.compile(function, dynamic=True, fullgraph=True, options={"cpp_wrapper": True} if cpp_wrapper else None)


def _quiet_value_range_analysis() -> None:
    """Silence torch's warning for each size expression its value-range analysis cannot bound (a power with a negative
    exponent of a dynamic size): the analysis handles the failure itself, but a GPU fit of reaction-diffusion printed
    144 such lines. Left alone where the user set the logger's level."""
    sympy_log = logging.getLogger("torch.utils._sympy.interp")
    if sympy_log.level == logging.NOTSET:
        sympy_log.setLevel(logging.ERROR)


def _copied_out(replayed: Callable) -> Callable:
    @functools.wraps(replayed)
    def call(*arguments):
        return replayed(*arguments).clone()

    return call


def new_training_step(device: torch.device) -> None:
    """Tell the CUDA-graph replays on ``device`` that a training step begins: the last step's graph memory may be reused.

    Nothing on a CPU, where the call would first import inductor's CUDA-graph machinery (about 2 s).
    """
    if device.type == "cuda":
        torch.compiler.cudagraph_mark_step_begin()


@functools.cache
def _lower_view_copies() -> None:
    """Let inductor fuse ``select_copy`` and ``slice_copy`` into its kernels, as it fuses ``select`` and ``slice``.

    A compiled loop (torch's ``scan``, otgb's solve of a small state) is differentiated through
    a graph in which every view is replaced by its copying twin (``state[:, 0]`` becomes
    ``select_copy``); torch 2.13's inductor has no lowering for these two, so each ran as a
    separate call through the dispatcher, 17 per step of a pendulum solve, about 30 % of its
    time. Here each is the view followed by a copy, which inductor fuses into the kernel that
    reads it. If inductor's lowering registry is not as expected, nothing is registered and
    the copies stay separate calls: slower, with the same values.
    """
    try:
        from torch._inductor import lowering
    except ImportError:
        return
    aten = torch.ops.aten
    select, slice_, clone = (getattr(lowering, name, None) for name in ("select", "slice_", "clone"))
    if None in (select, slice_, clone) or aten.select_copy.int in lowering.lowerings:
        return

    @lowering.register_lowering(aten.select_copy.int, type_promotion_kind=None)
    def select_copy(x, dim, index):
        return clone(select(x, dim, index))

    @lowering.register_lowering(aten.slice_copy.Tensor, type_promotion_kind=None)
    def slice_copy(x, dim=0, start=None, end=None, step=1):
        return clone(slice_(x, dim, start, end, step))


class EagerFallback:
    """``compiled(*arguments)``; where that raises, ``eager(*arguments)`` from then on, after one line saying why.

    ``key`` joins ``failed`` (the caller's record of what does not compile) at the first
    failure; ``describe(*arguments)`` says what runs eagerly (the line is ``otgb: <description>
    (<the error's first line>)``). An error that is the input's fault is raised again by the
    eager call, so it is never hidden.
    """

    def __init__(
        self,
        key: Hashable,
        compiled: Callable,
        eager: Callable,
        failed: set,
        describe: Callable[..., str],
        log: logging.Logger,
    ) -> None:
        self.key, self.compiled, self.eager, self.failed = key, compiled, eager, failed
        self.describe, self.log = describe, log

    def __call__(self, *arguments):
        if self.key in self.failed:
            return self.eager(*arguments)
        try:
            return self.compiled(*arguments)
        except Exception as error:  # the eager call below re-raises what is the input's fault
            result = self.eager(*arguments)
            self.failed.add(self.key)
            self.log.warning(f"otgb: {self.describe(*arguments)} ({first_line(error)[:300]})")
            return result
