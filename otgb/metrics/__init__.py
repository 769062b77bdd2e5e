"""Metrics on the joint evaluation sets."""

from otgb.metrics.errors import abs_err, nrmse
from otgb.metrics.mmd import mmd_rbf

__all__ = ["abs_err", "mmd_rbf", "nrmse"]
