"""A fitted coefficient's prior as data and as text: a config entry, report.json's distribution, the words a person reads."""

from __future__ import annotations

import json
from typing import Any

from otgb.physics.priors import Constant, Prior


def prior_dict(prior: Prior) -> dict[str, Any]:
    """A prior as a config entry (class_path / init_args)."""
    return {"class_path": f"otgb.physics.{prior.kind}", "init_args": dict(prior.init_args)}


def distribution(prior: Prior) -> dict[str, Any] | None:
    """``null`` for a constant coefficient, else the prior's kind and parameters."""
    if prior.is_constant:
        return None
    return {"kind": prior.kind.lower(), **prior.init_args}


def prior_text(prior: Prior) -> str:
    """A prior as a person reads it: a constant's value, else :func:`distribution_text`."""
    return f"{prior.value:.4g}" if isinstance(prior, Constant) else distribution_text(distribution(prior))


def distribution_text(distribution: dict[str, Any] | None) -> str:
    """A coefficient's distribution (:func:`distribution`) as a person reads it: "constant", "U(low, high)",
    "N(mean, std)" or "one of a, b"."""
    if distribution is None:
        return "constant"
    kind = distribution["kind"]
    if kind == "uniform":
        return f"U({distribution['low']:.4g}, {distribution['high']:.4g})"
    if kind == "normal":
        return f"N({distribution['mean']:.4g}, {distribution['std']:.4g})"
    if kind == "choice":
        return "one of " + ", ".join(f"{v:.4g}" for v in distribution["values"])
    return json.dumps(distribution)
