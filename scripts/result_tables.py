"""What the benchmark scripts share to render their result files as Markdown: ``from result_tables import row, header``
(a script's folder is on ``sys.path`` when it runs as ``python scripts/<name>.py``).

A mean ± sd over seeds is :func:`otgb.reports.mean_spread`; writing between a page's markers, :func:`otgb.reports.write_between`.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path


def row(cells: Iterable[object]) -> str:
    """One row of a Markdown table."""
    return "| " + " | ".join(map(str, cells)) + " |"


def header(columns: list[str]) -> list[str]:
    """A Markdown table's header row and the rule under it."""
    return [row(columns), "|---" * len(columns) + "|"]


def read_json(path: Path) -> dict:
    """A result file's content; {} where it does not exist (yet)."""
    return json.loads(path.read_text()) if path.exists() else {}


def results_in(folder: Path, pattern: str = "*.json") -> dict[Path, dict]:
    """Every result file under ``folder`` that matches ``pattern``, by path, in the order of the paths."""
    return {path: json.loads(path.read_text()) for path in sorted(Path(folder).glob(pattern))}


def spaced(number: int) -> str:
    """An integer with a space between its thousands: 1 000 000."""
    return f"{number:,}".replace(",", " ")


def listed(values: Iterable[float]) -> str:
    """Figures one after another (a per-seed column): "0.01234, 0.02345"."""
    return ", ".join(f"{v:.4g}" for v in values)
