"""Where a discovery run's time goes: wall seconds per stage, as ``stages.json`` and report.md's last section say.

A :class:`Stopwatch` times one run; the workflow's steps mark their stages with :func:`stage`. A stage's seconds are
its own: a stage entered inside another (the disagreement map a parametric form's check draws, say) is counted as
itself and not again in the outer one, so the stages' seconds add up to the run's timed wall time, the rest (setting
up, drawing the gap table's samples outside a stage) is "other". Outside a stopwatch, :func:`stage` costs nothing.
Wall times differ between runs of the same seed, so they stay out of report.json, whose numbers do not.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

OTHER = "other"  # the run's time in no stage

_RUNNING: list[Stopwatch] = []  # the stopwatches timing now, innermost last


@dataclass
class Stopwatch:
    """The seconds and entries of each stage of one run, in the order the stages were first entered."""

    seconds: dict[str, float] = field(default_factory=dict)
    calls: dict[str, int] = field(default_factory=dict)
    _open: list[str] = field(default_factory=list)
    _since: float = 0.0
    _started: float = 0.0
    total: float = 0.0

    def __enter__(self) -> Stopwatch:
        self._started = self._since = time.perf_counter()
        _RUNNING.append(self)
        return self

    def __exit__(self, *exc: object) -> None:
        _RUNNING.remove(self)
        self.total = time.perf_counter() - self._started
        self.seconds[OTHER] = max(0.0, self.total - sum(v for k, v in self.seconds.items() if k != OTHER))

    def _switch(self, to: str | None) -> None:
        """Count the time since the last switch to the open stage (none: "other"), then open ``to`` or close it."""
        now = time.perf_counter()
        if self._open:
            self.seconds[self._open[-1]] += now - self._since
        self._since = now
        if to is None:
            self._open.pop()
            return
        self._open.append(to)
        self.seconds.setdefault(to, 0.0)
        self.calls[to] = self.calls.get(to, 0) + 1

    def rows(self) -> list[dict[str, float | int | str]]:
        """Per stage its seconds, share of the total and entries, the longest first; "other" last."""
        staged = sorted((k for k in self.seconds if k != OTHER), key=lambda k: -self.seconds[k])
        total = self.total or 1.0
        rows = [
            {"stage": k, "seconds": self.seconds[k], "share": self.seconds[k] / total, "calls": self.calls[k]} for k in staged
        ]
        other = self.seconds.get(OTHER, 0.0)
        return rows + [{"stage": OTHER, "seconds": other, "share": other / total, "calls": 0}]

    def record(self) -> dict:
        """``stages.json``: the run's timed wall seconds and :meth:`rows`."""
        return {"total_seconds": self.total, "stages": self.rows()}


@contextmanager
def stage(name: str) -> Iterator[None]:
    """Time what runs inside as stage ``name`` of the innermost running :class:`Stopwatch` (module docstring)."""
    watch = _RUNNING[-1] if _RUNNING else None
    if watch is None:
        yield
        return
    watch._switch(name)
    try:
        yield
    finally:
        watch._switch(None)


def markdown_rows(record: dict | None) -> list[str]:
    """report.md's section on where the run's time went, from :meth:`Stopwatch.record` (nothing without one)."""
    if not record:
        return []
    lines = [
        "",
        "## Where the time went",
        "",
        f"Wall time of the run: {record['total_seconds'] / 60:.2f} min; each stage's own seconds (a stage inside another "
        "is counted once, as itself), the longest first.",
        "",
        "| stage | seconds | share | entered |",
        "|---|---|---|---|",
    ]
    rows = record["stages"]
    lines += [f"| {r['stage']} | {r['seconds']:.1f} | {r['share']:.1%} | {r['calls'] or '-'} |" for r in rows]
    return lines
