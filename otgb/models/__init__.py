"""Maps (grey-box) and critics."""

from otgb.models.critics import MLPCritic
from otgb.models.greybox import GreyBoxODE
from otgb.models.layers import ConditionalMLP

__all__ = ["ConditionalMLP", "GreyBoxODE", "MLPCritic"]
