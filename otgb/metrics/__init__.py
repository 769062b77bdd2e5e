"""Metrics on the joint evaluation sets: each as a function and as a torchmetrics Metric."""

from otgb.metrics.c2st import C2ST, c2st
from otgb.metrics.errors import NRMSE, AbsErr, abs_err, nrmse
from otgb.metrics.mmd import MMD, mmd2, mmd_median, mmd_multiscale
from otgb.metrics.mmdagg import MMDAgg, mmdagg
from otgb.metrics.samples import TwoSampleMetric, joint_samples

__all__ = [
    "C2ST",
    "MMD",
    "NRMSE",
    "AbsErr",
    "MMDAgg",
    "TwoSampleMetric",
    "abs_err",
    "c2st",
    "joint_samples",
    "mmd2",
    "mmd_median",
    "mmd_multiscale",
    "mmdagg",
    "nrmse",
]
