"""What the discovery workflow says while it runs: progress lines and diverged models, through :mod:`logging`.

Everything goes to the ``otgb.discover`` logger: progress at INFO, a model whose solve produced
NaN/Inf (a candidate, a resample's refit, a verification) at WARNING with the details in the
record's ``divergence`` attribute. ``otgb discover`` shows both on stderr
(:func:`show_on_stderr`; a model's divergence once per kind of step, :class:`OncePerModel`), away
from the progress bar's stream; a notebook user configures
``logging`` as usual. :class:`DivergenceLog` collects the divergences of one run for its report.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

logger = logging.getLogger("otgb.discover")
_STARTED = time.time()  # the clock of LogRecord.created


def progress(message: str) -> None:
    """A progress line (INFO)."""
    logger.info(message)


def rounded(value: Any) -> str:
    """Numbers, and lists or tuples of them, to 4 significant digits, for a log line."""
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(map(rounded, value)) + "]"
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def short(priors: list[Any]) -> str:
    """Priors as a person reads them in a log line: ``Constant(-0.2249)``, ``Uniform(-0.3676, -0.1192)``."""
    return rounded([f"{type(p).__name__}({', '.join(map(rounded, p.init_args.values()))})" for p in priors])


def diverged(
    what: str,
    terms: list[str],
    bad: int,
    total: int,
    first_inputs: list[float] | None = None,
    coefficients: list[str] | None = None,
) -> None:
    """Say that ``bad`` of ``total`` simulated trajectories of a model made of f_p + ``terms`` diverged in ``what``
    (WARNING, collected by :class:`DivergenceLog`): a fit or score counts the model as infinitely worse there, a
    verification leaves those trajectories out. ``coefficients``: the terms' priors, where the step simulated with
    given ones (a score, a verification), so that the report can tell the named model's own solves from others."""
    details = {"what": what, "terms": terms, "diverged": bad, "of": total, "first_inputs": first_inputs}
    details["coefficients"] = coefficients
    where = f" (first inputs theta={[float(f'{v:.4g}') for v in first_inputs]})" if first_inputs is not None else ""
    with_ = f" with coefficients {', '.join(coefficients)}" if coefficients else ""
    logger.warning(
        f"{what}: f_p + {terms or 'nothing'}{with_} diverged in {bad} of {total} trajectories{where}",
        extra={"divergence": details},
    )


def say_again(divergences: list[dict[str, Any]]) -> None:
    """Say divergence records (:func:`diverged`'s details) again: a fit read back from disk, or held back until its
    attempt succeeded (:func:`held_divergences`)."""
    for d in divergences:
        diverged(d["what"], d["terms"], d["diverged"], d["of"], d["first_inputs"], d["coefficients"])


@contextmanager
def held_divergences() -> Iterator[list[dict[str, Any]]]:
    """Within it, divergence records are held back (collected, not said): the caller says them with :func:`say_again`
    or drops them (an attempt that failed and is made again elsewhere)."""
    held: list[dict[str, Any]] = []

    def hold(record: logging.LogRecord) -> bool:
        if hasattr(record, "divergence"):
            held.append(record.divergence)
            return False
        return True

    logger.addFilter(hold)
    try:
        yield held
    finally:
        logger.removeFilter(hold)


class OncePerModel(logging.Filter):
    """Lets through the first divergence of each model (f_p plus the same terms) in each kind of step ("score",
    "fit", ...); its repeats with other coefficients (a family's or an interval's fits) go to the report only."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[tuple[str, tuple[str, ...]]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        details = getattr(record, "divergence", None)
        if details is None:
            return True
        key = (details["what"].split(" (")[0], tuple(details["terms"]))
        first = key not in self.seen
        self.seen.add(key)
        return first


class _Elapsed(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return f"otgb discover [{(record.created - _STARTED) / 60:.1f} min]: {record.getMessage()}"


def show_on_stderr() -> None:
    """Print the ``otgb.discover`` records (INFO and up) on stderr with the minutes since start (the handler once per
    process; each run's divergences shown afresh)."""
    for handler in logger.handlers:
        if getattr(handler, "otgb_discover", False):
            for once in handler.filters:
                if isinstance(once, OncePerModel):
                    once.seen.clear()
            return
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Elapsed())
    handler.addFilter(OncePerModel())
    handler.otgb_discover = True
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False


class DivergenceLog(logging.Handler):
    """Collects the divergence records of the ``otgb.discover`` logger while it is entered."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[dict[str, Any]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if hasattr(record, "divergence"):
            self.records.append(record.divergence)

    def __enter__(self) -> DivergenceLog:
        logger.addHandler(self)
        if logger.getEffectiveLevel() > logging.WARNING:
            logger.setLevel(logging.WARNING)
        return self

    def __exit__(self, *exc: object) -> None:
        logger.removeHandler(self)
