"""Building blocks shared by maps and critics."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from otgb.errors import InputError


def activation(name: str) -> nn.Module:
    """An activation module by its torch.nn class name ("ELU", "ReLU", "LeakyReLU", ...)."""
    cls = getattr(nn, name, None)
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise InputError(f"unknown activation {name!r}: expected a torch.nn class name such as 'ELU' or 'ReLU'")
    return cls()


def condition_encoder(cond_dim: int, features: int, activation_name: str) -> nn.Module | None:
    """The learned encoder of a condition (theta, z) into ``features`` numbers; None without a condition."""
    if cond_dim <= 0 or features <= 0:
        return None
    return nn.Sequential(nn.Linear(cond_dim, features), activation(activation_name))


def scale_initial_output(layer: nn.Module, output_scale: float) -> None:
    """Scale an output layer's initial weights by ``output_scale`` and zero its bias, so that a map starts near its base."""
    with torch.no_grad():
        layer.weight.mul_(output_scale)
        layer.bias.zero_()


class ConditionalMLP(nn.Module):
    """MLP f(u, c) whose condition c is encoded once and fed to every hidden layer.

    The condition (physics parameters theta, then latent z) goes through a learned encoder;
    its code is concatenated to the input of each layer (paper, App. E: "a learnable encoder
    of the conditional parameter whose output is concatenated to the input of each hidden
    layer"). The output layer starts scaled by ``output_scale`` so that a grey-box starts
    close to f_p.

    Args:
        in_shape: shape of u (flattened).
        out_shape: shape of the output.
        cond_dim: size of c (0: no condition, no encoder).
        hidden: widths of the hidden layers.
        cond_features: width of the condition code.
        activation_name: torch.nn class name of the activation, in the encoder and after
            each hidden layer.
        output_scale: factor on the output layer's initial weights (its bias starts at 0).
    """

    def __init__(
        self,
        in_shape: Sequence[int],
        out_shape: Sequence[int],
        cond_dim: int,
        hidden: Sequence[int] = (64, 64),
        cond_features: int = 16,
        activation_name: str = "ELU",
        output_scale: float = 0.01,
    ) -> None:
        super().__init__()
        self.out_shape = tuple(out_shape)
        in_dim, out_dim = math.prod(in_shape), math.prod(out_shape)
        code = cond_features if cond_dim > 0 else 0
        self.encoder = condition_encoder(cond_dim, code, activation_name)
        widths = [in_dim, *hidden]
        self.hidden = nn.ModuleList(nn.Linear(w + code, w_next) for w, w_next in zip(widths[:-1], widths[1:]))
        self.act = activation(activation_name)
        self.out = nn.Linear(widths[-1] + code, out_dim)
        scale_initial_output(self.out, output_scale)

    def forward(self, u: Tensor, cond: Tensor) -> Tensor:
        return self.conditioned(u, *self.condition(cond))

    def condition(self, cond: Tensor) -> tuple[Tensor, ...]:
        """What the condition adds to each layer, (B, width) per layer: its code times the layer's code columns, plus the bias.

        A layer's input is [h, code], so its output W [h, code] + b = W_h h + (W_code code + b): the
        bracket is the same at every stage of a solve, where c is constant, and is computed once.
        """
        code = self.encoder(cond) if self.encoder is not None else None
        return tuple(_code_part(layer, code, nn.functional.linear) for layer in (*self.hidden, self.out))

    def conditioned(self, u: Tensor, *parts: Tensor) -> Tensor:
        """f(u, c) from the condition's parts (:meth:`condition`)."""
        h = u.flatten(1)
        for layer, part in zip(self.hidden, parts):
            h = self.act(nn.functional.linear(h, _state_weight(layer, h)) + part)
        return (nn.functional.linear(h, _state_weight(self.out, h)) + parts[-1]).reshape(-1, *self.out_shape)


def _state_weight(layer: nn.Module, h: Tensor) -> Tensor:
    """The weight's columns (input channels) that act on the state's features h, (out, features, ...)."""
    return layer.weight[:, : h.shape[1]]


def _code_part(layer: nn.Module, code: Tensor | None, apply: Callable[..., Tensor]) -> Tensor:
    """``apply(code, W_code, b)``: the layer's output on the condition's code alone (the bias alone without a code)."""
    if code is None:
        return layer.bias.reshape(1, -1, *([1] * (layer.weight.dim() - 2)))
    features = layer.weight.shape[1] - code.shape[1]
    return apply(code, layer.weight[:, features:], layer.bias)


CONVOLUTIONS = {1: nn.Conv1d, 2: nn.Conv2d, 3: nn.Conv3d}


def convolution(dims: int) -> type[nn.Module]:
    """nn.Conv1d/2d/3d for ``dims`` spatial dimensions."""
    if dims not in CONVOLUTIONS:
        raise ValueError(f"convolutions over {dims} dimensions are not supported (expected 1, 2 or 3)")
    return CONVOLUTIONS[dims]


def _convolve_grid_major(layer: nn.Module, h: Tensor) -> Tensor:
    """``layer``'s 1-D convolution (no bias) of a grid-major ``h`` (B, L, C), grid-major: (B, L, out channels).

    Inside a compiled solve a 1-D convolution is its shifted views, side by side, and one matrix
    product, with the channels as the fastest axis: the compiler fuses the padding, the views and
    the activation before them into one contiguous, vectorised kernel, and calls one matrix product,
    where the library's convolution of a few channels on a short grid spends most of its time outside
    the arithmetic. With the channels first the views were a strided gather, 6x slower. An
    advection-diffusion grey-box solve and its backward on one thread: 140 ms with the library's
    convolution, 106 ms channels first, 59 ms grid-major. Eagerly, and on 2-D and 3-D grids (where the
    shifted views multiply the memory: 4x slower on reaction-diffusion's 32 x 32 grid), the library's
    convolution is faster and is used. The padding is the layer's own (``padding_mode`` "zeros" is
    ``F.pad``'s "constant").
    """
    weight = _state_weight(layer, h.transpose(1, 2))  # (out, C, size)
    size, length = weight.shape[-1], h.shape[1]
    mode = "constant" if layer.padding_mode == "zeros" else layer.padding_mode
    padded = F.pad(h.transpose(1, 2), (size // 2, size // 2), mode=mode).transpose(1, 2)  # (B, L + size - 1, C)
    rows = torch.cat([padded[:, k : k + length] for k in range(size)], dim=2)  # (B, L, size * C): offset-major
    return rows @ weight.permute(0, 2, 1).reshape(weight.shape[0], -1).t()


class ConditionalConvNet(nn.Module):
    """A fully convolutional f(u, c) on a field u (B, C, *space) with a condition c (B, cond_dim).

    The condition (theta, then z) is encoded once; its code is broadcast over space and
    concatenated as extra channels to the input of every layer, the convolutional form of
    :class:`ConditionalMLP`'s per-layer conditioning (paper, App. E; the official code injects
    (a, b) per layer). Being convolutional, the net learns a local, translation-invariant
    correction, as the missing terms of PDEs are. ``padding_mode`` should match the grid's
    boundary: "zeros" for Dirichlet, "circular" for periodic. The output layer starts scaled
    by ``output_scale`` so that a grey-box starts close to f_p.

    Args:
        in_shape: (C, *space) of u.
        out_shape: (C_out, *space) of the output (the same grid as u).
        cond_dim: size of c (0: no condition, no encoder).
        channels: widths of the hidden convolutions (one layer each, plus the output layer).
        kernel_size: size of every convolution's kernel (odd, so that the grid is kept).
        padding_mode: padding of the convolutions, "zeros" (Dirichlet) or "circular" (periodic).
        cond_features: channels of the condition code.
        activation_name: torch.nn class name of the activation, in the encoder and between
            the convolutions.
        output_scale: factor on the output layer's initial weights (its bias starts at 0).
    """

    def __init__(
        self,
        in_shape: Sequence[int],
        out_shape: Sequence[int],
        cond_dim: int,
        channels: Sequence[int] = (16, 16),
        kernel_size: int = 3,
        padding_mode: str = "zeros",
        cond_features: int = 8,
        activation_name: str = "ELU",
        output_scale: float = 0.01,
    ) -> None:
        super().__init__()
        if tuple(in_shape[1:]) != tuple(out_shape[1:]):
            raise ValueError(f"ConditionalConvNet: input {tuple(in_shape)} and output {tuple(out_shape)} need the same grid")
        conv = convolution(len(in_shape) - 1)
        self.grid = tuple(in_shape[1:])
        code = cond_features if cond_dim > 0 else 0
        self.encoder = condition_encoder(cond_dim, code, activation_name)
        widths = [in_shape[0], *channels, out_shape[0]]
        self.layers = nn.ModuleList(
            conv(w + code, w_next, kernel_size, padding=kernel_size // 2, padding_mode=padding_mode)
            for w, w_next in zip(widths[:-1], widths[1:])
        )
        self.act = activation(activation_name)
        scale_initial_output(self.layers[-1], output_scale)

    def forward(self, u: Tensor, cond: Tensor) -> Tensor:
        return self.conditioned(u, *self.condition(cond))

    def condition(self, cond: Tensor) -> tuple[Tensor, ...]:
        """What the condition adds to each layer, (B, out channels, *grid) per layer.

        A convolution is linear in its input channels: conv([h, code]) = conv_h(h) + conv_code(code),
        each with the same padding. The code's part is the same at every stage of a solve and is
        computed once (the code channels are also most of the first layer's input).
        """
        if self.encoder is None:
            return tuple(_code_part(layer, None, layer._conv_forward) for layer in self.layers)
        code = self.encoder(cond).reshape(*cond.shape[:1], -1, *([1] * len(self.grid))).expand(-1, -1, *self.grid)
        return tuple(_code_part(layer, code, layer._conv_forward) for layer in self.layers)

    def conditioned(self, u: Tensor, *parts: Tensor) -> Tensor:
        """f(u, c) from the condition's parts (:meth:`condition`)."""
        grid_major = len(self.grid) == 1 and torch.compiler.is_compiling()  # (B, L, C): see _convolve_grid_major
        h = u.transpose(1, 2) if grid_major else u
        for i, (layer, part) in enumerate(zip(self.layers, parts)):
            if grid_major:
                h = _convolve_grid_major(layer, h) + part.transpose(1, 2)
            else:
                h = layer._conv_forward(h, _state_weight(layer, h), None) + part
            if i < len(self.layers) - 1:
                h = self.act(h)
        return h.transpose(1, 2) if grid_major else h
