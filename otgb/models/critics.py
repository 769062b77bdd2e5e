"""Critics (potentials f_psi) on whole observed trajectories."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from otgb.errors import InputError
from otgb.models.layers import activation, convolution


class MLPCritic(nn.Module):
    """MLP on the flattened trajectory (paper, App. E: hidden [250, 100, 100, 50]).

    Args:
        trajectory_shape: (T, *obs_shape) of one trajectory.
        hidden: widths of the hidden layers.
        activation_name: torch.nn class name of the activation after each hidden layer.
    """

    def __init__(
        self, trajectory_shape: Sequence[int], hidden: Sequence[int] = (250, 100, 100, 50), activation_name: str = "ELU"
    ) -> None:
        super().__init__()
        widths = [math.prod(trajectory_shape), *hidden]
        layers: list[nn.Module] = []
        for w, w_next in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(w, w_next), activation(activation_name)]
        self.net = nn.Sequential(*layers, nn.Linear(widths[-1], 1))

    def forward(self, y: Tensor) -> Tensor:
        """y (N, T, *obs) -> (N,)."""
        return self.net(y.flatten(1)).squeeze(1)


class ResidualBlock(nn.Module):
    """act -> conv(stride) -> act -> conv, plus a strided 1x1 projection of the input.

    Args:
        conv: the convolution class (nn.Conv1d/2d/3d).
        c_in: input channels.
        c_out: output channels.
        stride: stride of the first convolution and of the projection.
        activation_name: torch.nn class name of the activation.
    """

    def __init__(self, conv: type[nn.Module], c_in: int, c_out: int, stride: int, activation_name: str) -> None:
        super().__init__()
        self.act = activation(activation_name)
        self.conv1 = conv(c_in, c_out, 3, stride=stride, padding=1)
        self.conv2 = conv(c_out, c_out, 3, padding=1)
        self.skip = conv(c_in, c_out, 1, stride=stride)

    def forward(self, h: Tensor) -> Tensor:
        return self.skip(h) + self.conv2(self.act(self.conv1(self.act(h))))


# On the CPU a 2-D or 3-D critic convolves channels-last: the library's convolutions then skip a
# reordering of every layer's input and output (the 3-D reaction-diffusion critic, one thread:
# forward 83 -> 45 ms, a critic update with its gradient penalty 862 -> 807 ms).
CHANNELS_LAST = {4: torch.channels_last, 5: torch.channels_last_3d}
CRITIC_PRECISIONS = ("32-true", "bf16-mixed")


class ConvCritic(nn.Module):
    """A convolutional residual critic on trajectories (N, T, C, *space).

    With ``time_as_channels`` the T frames of each of the C fields are stacked as channels
    and the convolutions run over space only (a 1-D residual network for advection-diffusion, a
    2-D one for reaction-diffusion); otherwise they run over (time, *space) with C channels.
    Each block halves the resolution; the features are averaged over
    the remaining positions and mapped to one score. No normalisation layers, so the
    per-sample gradient penalty stays well defined.

    Args:
        trajectory_shape: (T, C, *space) of one trajectory.
        channels: widths of the stem and of each residual block.
        time_as_channels: stack the T frames as channels and convolve over space only.
        activation_name: torch.nn class name of the activation.
        precision: the convolutions' arithmetic: "32-true" (float32), or "bf16-mixed" (under bfloat16
            autocast, float32 weights, the pooled features and the score in float32), with the
            convolutions rounded to bfloat16's 3 significant digits. It pays only where the processor
            multiplies bfloat16 natively (AMX, AVX512-BF16), and there only the critic's share of a step
            (docs/configs.md).
    """

    def __init__(
        self,
        trajectory_shape: Sequence[int],
        channels: Sequence[int] = (32, 64, 128),
        time_as_channels: bool = False,
        activation_name: str = "LeakyReLU",
        precision: str = "32-true",
    ) -> None:
        super().__init__()
        if precision not in CRITIC_PRECISIONS:
            raise InputError(f"model.critic.init_args.precision: {precision!r} is not one of {CRITIC_PRECISIONS}")
        self.bf16 = precision == "bf16-mixed"
        steps, fields, *space = trajectory_shape
        self.time_as_channels = time_as_channels
        conv = convolution(len(space) + (0 if time_as_channels else 1))
        self.stem = conv(steps * fields if time_as_channels else fields, channels[0], 3, padding=1)
        self.blocks = nn.Sequential(
            *(ResidualBlock(conv, c_in, c_out, 2, activation_name) for c_in, c_out in zip(channels[:-1], channels[1:]))
        )
        self.act = activation(activation_name)
        self.head = nn.Linear(channels[-1], 1)

    def forward(self, y: Tensor) -> Tensor:
        """y (N, T, C, *space) -> (N,)."""
        h = y.flatten(1, 2) if self.time_as_channels else y.movedim(1, 2)
        if h.device.type == "cpu" and h.dim() in CHANNELS_LAST:
            h = h.contiguous(memory_format=CHANNELS_LAST[h.dim()])
        with torch.autocast(h.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            h = self.act(self.blocks(self.stem(h)))
        return self.head(h.float().flatten(2).mean(dim=2)).squeeze(1)
