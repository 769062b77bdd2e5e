"""Finished coefficient fits on disk, so that a stopped ``otgb discover`` run resumes where it stopped.

Every distribution-matching fit of a discovery run (:func:`otgb.discovery.refine.fit`) is a
deterministic function of its inputs: the physics, the candidate terms and their starts, the prior
family, the fit's steps, batch and seed, and the measured trajectories it matches and is scored on.
With ``--discover.fit_cache DIR`` each finished fit is written to DIR under a key of all of these
and of otgb's own source code (a fit of other code is never reused); a run that asks for the same
fit again reads it instead of fitting. A run stopped part way (a session's end, a batch job's time
limit) and started again with the same DIR and config repeats its cheap steps and reads its fits
back, so it reaches the same result as a run that was never stopped, and carries on from there. The
95 % intervals of a fitted model (:func:`otgb.discovery.intervals.fitted_intervals`) are kept the same way.

A reaction-diffusion fit of 1024 simulated 2 x 32 x 32 fields takes minutes on a CPU and a
discovery run makes dozens, so such a run can take longer than one session or job.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import otgb
from otgb.discovery.log import DivergenceLog, logger, progress, say_again
from otgb.errors import InputError


class FitCache:
    """A folder of finished fits, one file per fit, named by the hash of everything the fit depends on.

    A file holds plain data (numbers, strings, lists, tensors), read back with ``torch.load(weights_only=True)``: a
    folder shared with others cannot make a run execute code.
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise InputError(f"discover.fit_cache={str(folder)!r}: expected a folder (or a path to create one), got a file")
        self.read = 0  # fits of earlier, stopped attempts that this run read back instead of fitting
        self.seconds_read = 0.0  # the time those fits took when they ran
        self.written: set[str] = set()  # the keys of the fits this run made
        self.writable = True  # False after a write failed: the fits are then not kept

    def key(self, physics: Any, measured: Tensor, heldout: Tensor, **inputs: Any) -> str:
        """The hash of a fit's inputs: ``physics`` (its class, settings and measurement noise in force), the
        ``measured`` and ``heldout`` trajectories, the fit's other arguments ``inputs``, and otgb's source."""
        digest = hashlib.sha256()
        settings = getattr(physics, "init_args", {})
        parts = (type(physics).__qualname__, sorted(settings.items()), getattr(physics, "_measurement_noise", None))
        for part in (*parts, sorted(inputs.items()), torch.__version__, _source_digest()):
            digest.update(repr(part).encode())
        for tensor in (measured, heldout):
            digest.update(repr((tuple(tensor.shape), tensor.dtype)).encode())
            digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        return digest.hexdigest()[:32]

    def record(self, key: str, fit: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """The record stored under ``key``, its divergence warnings said again as when it ran; else ``fit()``'s record
        (plain data), stored."""
        stored = self.get(key)
        if stored is not None:
            say_again(stored["divergences"])
            if key not in self.written:  # not a repeat of this run's own fit
                if self.read == 0:
                    progress(f"fit cache: reading finished fits from {self.folder}")
                self.read += 1
                self.seconds_read += stored["seconds"]
            return stored["record"]
        started = time.perf_counter()
        with DivergenceLog() as log:
            record = fit()
        self.written.add(key)
        self.put(key, {"record": record, "divergences": log.records, "seconds": time.perf_counter() - started})
        return record

    def finished(self) -> int:
        """The fits and intervals of this run that are on disk: those it made and those of earlier attempts it read back."""
        return (len(self.written) if self.writable else 0) + self.read

    def summary(self) -> dict[str, Any]:
        """Where the fits are stored, how many this run read back, and the seconds they took when they ran (a resumed
        run's wall time plus these is the time of a run that was never stopped)."""
        return {"folder": str(self.folder), "fits_read": self.read, "seconds_read": self.seconds_read}

    def get(self, key: str) -> dict[str, Any] | None:
        """The file stored under ``key``, or None (none stored, or a file that cannot be read: it is fitted again)."""
        path = self.folder / f"{key}.pt"
        if not path.is_file():
            return None
        try:
            return torch.load(path, weights_only=True)
        except Exception as error:  # a file cut short outside otgb's atomic writes, or not otgb's: fit again, replace it
            progress(f"fit cache: {path.name} could not be read ({type(error).__name__}); fitting again")
            return None

    def put(self, key: str, stored: dict[str, Any]) -> None:
        """Store ``stored`` under ``key``, written whole or not at all (a stop mid-write leaves no file). A folder that
        cannot be written costs one warning, not the run: its fits are then not kept."""
        if not self.writable:
            return
        partial = self.folder / f".{key}.{os.getpid()}.partial"
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            torch.save(stored, partial)
            os.replace(partial, self.folder / f"{key}.pt")
        except (OSError, RuntimeError) as error:  # RuntimeError: torch.save's writer on a full disk
            self.writable = False
            with contextlib.suppress(OSError):
                partial.unlink(missing_ok=True)
            reason = getattr(error, "strerror", None) or str(error) or type(error).__name__
            logger.warning(f"fit cache: cannot write {self.folder} ({reason}); this run's fits are not kept for a rerun")


@functools.cache
def _source_digest() -> str:
    """The hash of otgb's Python source: a fit stored by other code is not read back."""
    digest = hashlib.sha256()
    root = Path(otgb.__file__).parent
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()
