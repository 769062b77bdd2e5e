"""Third-party messages known to be harmless in otgb's runs, filtered where they arise, each with the reason.

Only these exact messages are dropped; every other warning and log line of Lightning and torch
reaches the terminal as before.
"""

from __future__ import annotations

import logging
import warnings


class _Drop(logging.Filter):
    """Drops the log records whose message contains ``text``."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.text = text

    def filter(self, record: logging.LogRecord) -> bool:
        return self.text not in record.getMessage()


def quiet_known_harmless() -> None:
    """Install the filters (idempotent: ``warnings`` keeps one copy of each filter, loggers one of each object)."""
    # Lightning advertises its cloud logger at the start of every fit, says that no TPU is there, and that it loads
    # the training loader to count its steps (the learning-rate schedules ask for that count): none is about the
    # run (otgb runs on CPUs and CUDA GPUs; the GPU line stays).
    # A fit's one epoch is its simulation budget (otgb/configs/defaults.yaml), so "`max_epochs=1` reached" says only that
    # the budget was spent, and reads as if the run had stopped short; a fit ended by max_steps or max_time still says so.
    harmless = ("litlogger", "TPU available: False", "to estimate number of stepping batches", "`max_epochs=1` reached")
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, _Drop) for f in logger.filters):
            for text in harmless:
                logger.addFilter(_Drop(text))
    # The source stream is an IterableDataset whose __len__ is the number of steps its budget buys; its
    # DataLoader workers take disjoint items (otgb.data.stream), so the length Lightning warns about is exact.
    warnings.filterwarnings("ignore", message="Your `IterableDataset` has `__len__` defined", category=UserWarning)
    # Lightning's own call of a torch pytree API that torch deprecated (lightning/pytorch/utilities/_pytree.py):
    # nothing in otgb or in a user's config causes it or can change it.
    warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated")
