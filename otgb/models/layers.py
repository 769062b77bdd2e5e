"""Building blocks shared by maps and critics."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn


def activation(name: str) -> nn.Module:
    """An activation module by its torch.nn class name ("ELU", "ReLU", "LeakyReLU", ...)."""
    cls = getattr(nn, name, None)
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise ValueError(f"unknown activation {name!r}: expected a torch.nn class name such as 'ELU' or 'ReLU'")
    return cls()


class ConditionalMLP(nn.Module):
    """MLP f(u, c) whose condition c is encoded once and fed to every hidden layer.

    The condition (physics parameters theta, then latent z) goes through a learned encoder;
    its code is concatenated to the input of each layer (paper, App. E: "a learnable encoder
    of the conditional parameter whose output is concatenated to the input of each hidden
    layer"). The output layer starts scaled by ``output_scale`` so that a grey-box starts
    close to f_p.

    Args:
        in_shape: shape of u (flattened). out_shape: shape of the output.
        cond_dim: size of c. hidden: widths of the hidden layers.
        cond_features: width of the condition code.
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
        self.encoder = nn.Sequential(nn.Linear(cond_dim, code), activation(activation_name)) if code else None
        widths = [in_dim, *hidden]
        self.hidden = nn.ModuleList(nn.Linear(w + code, w_next) for w, w_next in zip(widths[:-1], widths[1:]))
        self.act = activation(activation_name)
        self.out = nn.Linear(widths[-1] + code, out_dim)
        with torch.no_grad():
            self.out.weight.mul_(output_scale)
            self.out.bias.zero_()

    def forward(self, u: Tensor, cond: Tensor) -> Tensor:
        h = u.flatten(1)
        code = self.encoder(cond) if self.encoder is not None else None
        for layer in self.hidden:
            h = self.act(layer(h if code is None else torch.cat([h, code], dim=1)))
        h = h if code is None else torch.cat([h, code], dim=1)
        return self.out(h).reshape(-1, *self.out_shape)
