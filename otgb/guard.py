"""Guarded updates: an update whose loss or gradients are NaN/Inf is skipped, and too many in a row stop the run.

A skipped update leaves the weights and the optimiser's state (Adam's moments) as they were,
so one bad batch costs one update. ``limit`` consecutive skips mean that training itself has
diverged: the run stops with :class:`TrainingDiverged`, whose one-line message names what
diverged, the learning rates and the likely causes.
"""

from __future__ import annotations

from dataclasses import dataclass

LIKELY_CAUSES = {
    "map": "a map learning rate too high (model.map_optimizer.init_args.lr), or a learned correction that makes the solve "
    "blow up (set model.grad_clip, or a smaller solver step in the physics)",
    "critic": "a critic learning rate too high (model.critic_optimizer.init_args.lr), or too weak a gradient penalty "
    "(model.gp_weight)",
}


class TrainingDiverged(FloatingPointError):
    """Training produced NaN/Inf in too many consecutive updates; the message says what, and what to try."""


@dataclass
class UpdateGuard:
    """Counts skipped updates: all of them (``skipped``) and the current run of them (``consecutive``)."""

    limit: int
    skipped: int = 0
    consecutive: int = 0
    network: str = ""
    reason: str = ""

    def passed(self) -> None:
        self.consecutive = 0

    def failed(self, network: str, reason: str) -> bool:
        """Count a skipped update of ``network`` ("map" or "critic"); True once ``limit`` came in a row."""
        self.skipped += 1
        self.consecutive += 1
        self.network, self.reason = network, reason
        return self.consecutive >= self.limit

    def message(self, learning_rates: dict[str, float], saved: str | None) -> str:
        what = f"{self.consecutive} update(s) in a row gave NaN/Inf, the last one of the {self.network} ({self.reason})"
        return diagnosis(what, self.network, learning_rates, saved)


def diagnosis(what: str, network: str, learning_rates: dict[str, float], saved: str | None) -> str:
    """One line: what diverged, the learning rates, the likely causes for ``network`` and where the last good state is."""
    rates = ", ".join(f"{name} {lr:g}" for name, lr in learning_rates.items())
    rates = f"; learning rates: {rates}" if rates else ""
    state = f"; the last good state is in {saved} (resume with --ckpt_path {saved})" if saved else ""
    return f"training diverged: {what}{rates}; likely causes: {LIKELY_CAUSES[network]}{state}"
