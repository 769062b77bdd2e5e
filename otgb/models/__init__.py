"""Maps (grey-box and black-box) and critics."""

from otgb.models.blackbox import LSTMMap, ResNet1dMap, UNet3dMap
from otgb.models.critics import ConvCritic, MLPCritic
from otgb.models.greybox import GreyBoxODE
from otgb.models.layers import ConditionalConvNet, ConditionalMLP
from otgb.models.physics_maps import CompletePhysicsMap, IdentityMap
from otgb.models.separable import SeparableCorrection

__all__ = [
    "CompletePhysicsMap",
    "ConditionalConvNet",
    "ConditionalMLP",
    "ConvCritic",
    "GreyBoxODE",
    "IdentityMap",
    "LSTMMap",
    "MLPCritic",
    "ResNet1dMap",
    "SeparableCorrection",
    "UNet3dMap",
]
