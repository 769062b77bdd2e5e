"""Black-box maps: networks that map the source trajectory x (with theta and z) to y directly.

The paper's baselines (its Table 1, "BB"; App. E): no f_p inside the map, which sees f_p only
through its input x. Each is one class with the grey-box's interface ``(physics, z_dim)`` and
``forward(x, x0, theta, z) -> y`` (B, T, *obs), selected by ``model.transport_map.class_path``:

- :class:`LSTMMap`: an LSTM over the time steps (the pendulum's map in the paper);
- :class:`ResNet1dMap`: a 1-D residual conv net over the grid, the frames as channels
  (advection-diffusion);
- :class:`UNet3dMap`: a 3-D U-Net over (time, grid) (reaction-diffusion).

Every map outputs y = x + g(x, theta, z), its last layer scaled by ``output_scale`` so that it
starts near the identity, as the grey-box starts near f_p: the comparison is between what the
two can learn, not where they start. The condition (theta, then z) is encoded once and fed
to every layer, as in the grey-box's correction networks.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch
from torch import Tensor, nn

from otgb.errors import InputError
from otgb.models.layers import activation, condition_encoder, scale_initial_output
from otgb.physics.base import PhysicsModel, raise_if_diverged


class BlackBoxMap(nn.Module, ABC):
    """Shared parts: the condition's encoder and the residual output y = x + g(x, code)."""

    def __init__(self, physics: PhysicsModel, z_dim: int, cond_features: int, activation_name: str) -> None:
        super().__init__()
        self.trajectory_shape = tuple(physics.trajectory_shape)
        self.cond_dim = physics.theta_dim + z_dim
        self.cond_features = cond_features if self.cond_dim > 0 else 0
        self.encoder = condition_encoder(self.cond_dim, self.cond_features, activation_name)

    def code(self, theta: Tensor, z: Tensor) -> Tensor:
        """The condition's code (B, cond_features); (B, 0) without a condition."""
        if self.encoder is None:
            return theta.new_zeros(len(theta), 0)
        return self.encoder(torch.cat([theta, z], dim=1))

    def forward(self, x: Tensor, initial_state: Tensor, theta: Tensor, z: Tensor, signals: Tensor | None = None) -> Tensor:
        """y = x + g(x, theta, z), (B, T, *obs); ``initial_state`` and the input ``signals`` are not used (x, simulated
        with them, holds them)."""
        if tuple(x.shape[1:]) != self.trajectory_shape:
            raise ValueError(f"{type(self).__name__}: source trajectories {tuple(x.shape[1:])}, expected {self.trajectory_shape}")
        y = x + self.residual(x, self.code(theta, z))
        raise_if_diverged(y, type(self).__name__, theta)
        return y

    @abstractmethod
    def residual(self, x: Tensor, code: Tensor) -> Tensor:
        """g(x, code), shaped like x."""


class LSTMMap(BlackBoxMap):
    """An LSTM over time: at step t it reads x_t and the condition's code and outputs y_t - x_t.

    Args:
        physics: f_p, whose inputs and observation the map takes and gives.
        z_dim: dimension of the latent z.
        hidden: width of the LSTM.
        layers: stacked LSTM layers (the paper's pendulum map has 4).
        cond_features: width of the condition's code.
        activation_name: of the encoder.
        output_scale: factor on the output layer's initial weights.
    """

    def __init__(
        self,
        physics: PhysicsModel,
        z_dim: int,
        hidden: int = 64,
        layers: int = 4,
        cond_features: int = 16,
        activation_name: str = "ELU",
        output_scale: float = 0.01,
    ) -> None:
        super().__init__(physics, z_dim, cond_features, activation_name)
        features = math.prod(self.trajectory_shape[1:])
        self.lstm = nn.LSTM(features + self.cond_features, hidden, num_layers=layers, batch_first=True)
        self.out = nn.Linear(hidden, features)
        scale_initial_output(self.out, output_scale)

    def residual(self, x: Tensor, code: Tensor) -> Tensor:
        steps = x.shape[1]
        inputs = torch.cat([x.flatten(2), code.unsqueeze(1).expand(-1, steps, -1)], dim=2)
        hidden, _ = self.lstm(inputs)
        return self.out(hidden).reshape(x.shape)


class ResidualBlock1d(nn.Module):
    """Two 1-D convolutions with a skip connection; the condition's code enters as extra channels."""

    def __init__(self, channels: int, code: int, kernel_size: int, padding_mode: str, activation_name: str) -> None:
        super().__init__()
        conv = lambda c_in: nn.Conv1d(c_in, channels, kernel_size, padding=kernel_size // 2, padding_mode=padding_mode)  # noqa: E731
        self.conv1, self.conv2 = conv(channels + code), conv(channels + code)
        self.act = activation(activation_name)

    def forward(self, h: Tensor, code: Tensor) -> Tensor:
        inner = self.act(self.conv1(torch.cat([h, code], dim=1)))
        return self.act(h + self.conv2(torch.cat([inner, code], dim=1)))


class ResNet1dMap(BlackBoxMap):
    """A 1-D ResNet over the grid of a field on one spatial axis; all frames (and channels) are its channels.

    Args:
        physics: f_p, whose inputs and observation the map takes and gives; the observed trajectory is (T, C, S).
        z_dim: dimension of the latent z.
        channels: width of the residual blocks.
        blocks: how many.
        kernel_size: of every convolution (odd).
        padding_mode: "zeros" (Dirichlet) or "circular" (periodic).
        cond_features: channels of the condition's code.
        activation_name: of the encoder.
        output_scale: factor on the output layer's initial weights.
    """

    def __init__(
        self,
        physics: PhysicsModel,
        z_dim: int,
        channels: int = 32,
        blocks: int = 4,
        kernel_size: int = 3,
        padding_mode: str = "zeros",
        cond_features: int = 8,
        activation_name: str = "ELU",
        output_scale: float = 0.01,
    ) -> None:
        super().__init__(physics, z_dim, cond_features, activation_name)
        if len(self.trajectory_shape) != 3:
            raise InputError(
                f"model.transport_map: ResNet1dMap needs trajectories (T, C, S) on one spatial axis, "
                f"got {self.trajectory_shape} from {type(physics).__name__}"
            )
        frames = self.trajectory_shape[0] * self.trajectory_shape[1]
        pad = dict(padding=kernel_size // 2, padding_mode=padding_mode)
        self.stem = nn.Conv1d(frames + self.cond_features, channels, kernel_size, **pad)
        self.blocks = nn.ModuleList(
            ResidualBlock1d(channels, self.cond_features, kernel_size, padding_mode, activation_name) for _ in range(blocks)
        )
        self.out = nn.Conv1d(channels + self.cond_features, frames, kernel_size, **pad)
        self.act = activation(activation_name)
        scale_initial_output(self.out, output_scale)

    def residual(self, x: Tensor, code: Tensor) -> Tensor:
        cells = x.shape[-1]
        code = code.unsqueeze(2).expand(-1, -1, cells)
        h = self.act(self.stem(torch.cat([x.flatten(1, 2), code], dim=1)))
        for block in self.blocks:
            h = block(h, code)
        return self.out(torch.cat([h, code], dim=1)).reshape(x.shape)


class UNet3dMap(BlackBoxMap):
    """A 3-D U-Net over (time, grid) of a field on two spatial axes, with one level per entry of ``channels``.

    Each level halves the grid (not the time axis) on the way down and doubles it on the way
    up, with skip connections; the condition's code enters every convolution as extra channels.

    Args:
        physics: f_p, whose inputs and observation the map takes and gives; the observed trajectory is
            (T, C, H, W), H and W divisible by 2 ** (len(channels) - 1).
        z_dim: dimension of the latent z.
        channels: widths of the levels, finest first.
        padding_mode: "zeros" (Dirichlet) or "circular" (periodic).
        cond_features: width of the condition's code.
        activation_name: of the encoder.
        output_scale: factor on the output layer's initial weights.
    """

    def __init__(
        self,
        physics: PhysicsModel,
        z_dim: int,
        channels: tuple[int, ...] = (16, 32),
        padding_mode: str = "circular",
        cond_features: int = 8,
        activation_name: str = "ELU",
        output_scale: float = 0.01,
    ) -> None:
        super().__init__(physics, z_dim, cond_features, activation_name)
        if len(self.trajectory_shape) != 4:
            raise InputError(
                f"model.transport_map: UNet3dMap needs trajectories (T, C, H, W) on two spatial axes, "
                f"got {self.trajectory_shape} from {type(physics).__name__}"
            )
        factor = 2 ** (len(channels) - 1)
        if any(n % factor for n in self.trajectory_shape[2:]):
            grid = self.trajectory_shape[2:]
            levels = len(channels)
            raise InputError(f"model.transport_map: UNet3dMap's grid {grid} must be divisible by {factor} for {levels} levels")
        fields, code = self.trajectory_shape[1], self.cond_features
        conv = lambda c_in, c_out: nn.Conv3d(c_in + code, c_out, 3, padding=1, padding_mode=padding_mode)  # noqa: E731
        widths = [fields, *channels]
        self.down = nn.ModuleList(conv(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.up = nn.ModuleList(conv(channels[i + 1] + channels[i], channels[i]) for i in reversed(range(len(channels) - 1)))
        self.out = nn.Conv3d(channels[0] + code, fields, 1)
        self.pool = nn.AvgPool3d((1, 2, 2))
        self.upsample = nn.Upsample(scale_factor=(1, 2, 2), mode="nearest")
        self.act = activation(activation_name)
        scale_initial_output(self.out, output_scale)

    def residual(self, x: Tensor, code: Tensor) -> Tensor:
        with_code = lambda h: torch.cat([h, code[:, :, None, None, None].expand(-1, -1, *h.shape[2:])], dim=1)  # noqa: E731
        h, skips = x.transpose(1, 2), []  # (B, C, T, H, W)
        for i, layer in enumerate(self.down):
            if i > 0:
                skips.append(h)
                h = self.pool(h)
            h = self.act(layer(with_code(h)))
        for layer in self.up:
            h = self.act(layer(with_code(torch.cat([self.upsample(h), skips.pop()], dim=1))))
        return self.out(with_code(h)).transpose(1, 2)
