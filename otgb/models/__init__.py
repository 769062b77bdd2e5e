"""Maps (grey-box) and critics."""

from otgb.models.critics import ConvCritic, MLPCritic
from otgb.models.greybox import GreyBoxODE
from otgb.models.layers import ConditionalConvNet, ConditionalMLP

__all__ = ["ConditionalConvNet", "ConditionalMLP", "ConvCritic", "GreyBoxODE", "MLPCritic"]
