"""The log records a test reads, each counted once whatever pytest and Lightning attach.

pytest's ``caplog`` listens on the root logger and, from pytest 9 on, also on every logger that does not propagate
when a test phase starts (Lightning's ``lightning.pytorch``, otgb discover's ``otgb.discover``), so a record may reach
it once or twice, or not at all, by the pytest release and the order of tests. ``records_of`` listens on the loggers
named and keeps each record once."""

import logging
from collections.abc import Iterator
from contextlib import contextmanager


class _OncePerRecord(logging.Handler):
    def __init__(self, level: int) -> None:
        super().__init__(level)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if all(record is not seen for seen in self.records):  # a record passes each listened logger on its way up
            self.records.append(record)


@contextmanager
def records_of(*names: str, level: int = logging.INFO) -> Iterator[list[logging.LogRecord]]:
    """The records at ``level`` and above that the loggers ``names`` and their children emit inside the block, in order,
    once each (the loggers' levels lowered to ``level`` meanwhile, then restored)."""
    handler = _OncePerRecord(level)
    loggers = [logging.getLogger(name) for name in names]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.addHandler(handler)
        if logger.getEffectiveLevel() > level:
            logger.setLevel(level)
    try:
        yield handler.records
    finally:
        for logger, before in zip(loggers, levels):
            logger.removeHandler(handler)
            logger.setLevel(before)


def text_of(records: list[logging.LogRecord]) -> str:
    """The records' messages, a line each."""
    return "\n".join(record.getMessage() for record in records)
