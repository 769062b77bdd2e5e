"""The paper's C2ST judge network, forward and backward, as one loop over the rows (numba), on the CPU.

:class:`otgb.metrics.classifiers.PaperConvNet` is three kernel-3 convolutions of 3 channels over a
row of a thousand features, average pooling and one logit. In torch each layer is a pass over the
whole batch's activations, a few arithmetic operations per number read, so a training step is
memory traffic. Here each row goes through the whole network, forward and back, while its
activations (9 x the row's length) stay in the processor's cache, and the gradients of the 63
convolution weights and the linear layer are summed row by row. The backward pass computes the
row's forward again rather than storing it. The arithmetic is the network's, in float32, summed in
another order (the results agree with torch's to float32 rounding, ``tests/test_metrics.py``).
The loops release the GIL, so the C2ST's folds trained in threads run at once.
``scripts/speed_benchmark.py judges`` times it against the torch path.

Used where the rows are float32 on the CPU, outside autocast, and numba imports; elsewhere
(a GPU, bfloat16, no numba) the network runs on torch's operations, after one line saying why
where numba is missing. The compiled loops are cached on disk (numba's ``cache=True``): the first
use on a machine compiles them (seconds), later processes load them.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from torch import Tensor

log = logging.getLogger("otgb.metrics")

try:
    from numba import njit
except Exception as error:  # numba missing or broken on this platform: the torch path runs
    UNAVAILABLE = f"{type(error).__name__}: {error}"

    def njit(**options):  # the loops stay Python functions, never called
        return lambda function: function
else:
    UNAVAILABLE = ""

_said_why = False


def available(rows: Tensor) -> bool:
    """Whether the fused loops can run the network on ``rows`` (float32 on the CPU, outside autocast, numba)."""
    global _said_why
    if rows.device.type != "cpu" or rows.dtype != torch.float32 or torch.is_autocast_enabled("cpu"):
        return False
    if UNAVAILABLE and not _said_why:
        log.warning(f"otgb: the paper's C2ST judge runs on torch's convolutions, slower: numba did not import ({UNAVAILABLE})")
        _said_why = True
    return not UNAVAILABLE


class FusedPaperConvNet(torch.autograd.Function):
    """``PaperConvNet``'s logits of ``rows`` (B, L) from its parameters; the backward gives the parameters' gradients."""

    @staticmethod
    def forward(ctx, rows: Tensor, *parameters: Tensor) -> Tensor:
        arrays = _arrays(rows, parameters)
        ctx.save_for_backward(rows, *parameters)
        return torch.from_numpy(logits(*arrays))

    @staticmethod
    def backward(ctx, grad_logits: Tensor) -> tuple[Tensor | None, ...]:
        rows, *parameters = ctx.saved_tensors
        arrays = _arrays(rows, parameters)
        dlogits = grad_logits.detach().contiguous().numpy()
        grads = gradients(arrays[0], dlogits, *arrays[1:])
        return (None, *(torch.from_numpy(g).reshape(p.shape) for g, p in zip(grads, parameters)))


def _arrays(rows: Tensor, parameters: tuple[Tensor, ...]) -> list[np.ndarray]:
    """float32 numpy views: the rows, then conv weights (3, C, 3) and biases per layer, the linear weight flat and bias."""
    flat = [p.detach().contiguous() for p in parameters]
    flat[-2] = flat[-2].reshape(-1)
    return [rows.detach().contiguous().numpy(), *(p.numpy() for p in flat)]


# --- the loops (compiled by numba at first call, or loaded from its cache) ----------------------
FAST = {"reassoc", "contract", "nsz"}  # vectorised sums (another order of float32 additions), fused multiply-adds
SLOPE = 0.01  # LeakyReLU's default negative slope, as in PaperConvNet


@njit(inline="always", fastmath=FAST)
def conv_layer(src, w, b, z, a, length):
    """z = conv(src) (kernel 3, zero padding 1), a = LeakyReLU(z)."""
    for o in range(w.shape[0]):
        z[o, :length] = b[o]
        for c in range(w.shape[1]):
            for i in range(length):
                z[o, i] += w[o, c, 1] * src[c, i]
            for i in range(1, length):
                z[o, i] += w[o, c, 0] * src[c, i - 1]
            for i in range(length - 1):
                z[o, i] += w[o, c, 2] * src[c, i + 1]
        for i in range(length):
            a[o, i] = z[o, i] if z[o, i] > 0 else z[o, i] * np.float32(SLOPE)


@njit(inline="always", fastmath=FAST)
def row_logit(x, w1, b1, w2, b2, w3, b3, wl, bl, z, a, pooled):
    """One row's logit; leaves the pre-activations z (3, 3, L), activations a and pooled values behind."""
    length, n = x.shape[1], x.shape[1] // 3
    conv_layer(x, w1, b1, z[0], a[0], length)
    conv_layer(a[0], w2, b2, z[1], a[1], length)
    conv_layer(a[1], w3, b3, z[2], a[2], length)
    logit = bl[0]
    for c in range(3):
        for j in range(n):
            pooled[c, j] = (a[2, c, 3 * j] + a[2, c, 3 * j + 1] + a[2, c, 3 * j + 2]) * np.float32(1 / 3)
            logit += wl[c * n + j] * pooled[c, j]
    return logit


@njit(inline="always", fastmath=FAST)
def leaky_backward(grad, z, length):
    for c in range(grad.shape[0]):
        for i in range(length):
            grad[c, i] *= np.float32(1) if z[c, i] > 0 else np.float32(SLOPE)


@njit(inline="always", fastmath=FAST)
def conv_backward(dz, src, w, dw, db, dsrc, length):
    """Adds the layer's weight and bias gradients; writes the gradient of its input into dsrc (if it has rows)."""
    for o in range(w.shape[0]):
        db[o] += dz[o, :length].sum()
        for c in range(w.shape[1]):
            g0, g1, g2 = np.float32(0), np.float32(0), np.float32(0)
            for i in range(length):
                g1 += dz[o, i] * src[c, i]
            for i in range(1, length):
                g0 += dz[o, i] * src[c, i - 1]
            for i in range(length - 1):
                g2 += dz[o, i] * src[c, i + 1]
            dw[o, c, 0] += g0
            dw[o, c, 1] += g1
            dw[o, c, 2] += g2
    for c in range(dsrc.shape[0]):
        dsrc[c, :length] = 0
        for o in range(w.shape[0]):
            for i in range(length):
                dsrc[c, i] += w[o, c, 1] * dz[o, i]
            for i in range(length - 1):
                dsrc[c, i] += w[o, c, 0] * dz[o, i + 1]
            for i in range(1, length):
                dsrc[c, i] += w[o, c, 2] * dz[o, i - 1]


@njit(nogil=True, cache=True, fastmath=FAST)
def logits(rows, w1, b1, w2, b2, w3, b3, wl, bl):
    length = rows.shape[1]
    z, a = np.empty((3, 3, length), np.float32), np.empty((3, 3, length), np.float32)
    pooled, out = np.empty((3, length // 3), np.float32), np.empty(rows.shape[0], np.float32)
    for r in range(rows.shape[0]):
        out[r] = row_logit(rows[r : r + 1], w1, b1, w2, b2, w3, b3, wl, bl, z, a, pooled)
    return out


@njit(nogil=True, cache=True, fastmath=FAST)
def gradients(rows, dlogits, w1, b1, w2, b2, w3, b3, wl, bl):
    length = rows.shape[1]
    n = length // 3
    g1, g2, g3 = np.zeros_like(w1), np.zeros_like(w2), np.zeros_like(w3)
    gb1, gb2, gb3 = np.zeros_like(b1), np.zeros_like(b2), np.zeros_like(b3)
    gl, gbl = np.zeros_like(wl), np.zeros_like(bl)
    z, a = np.empty((3, 3, length), np.float32), np.empty((3, 3, length), np.float32)
    pooled = np.empty((3, n), np.float32)
    d, e, no_input = np.empty((3, length), np.float32), np.empty((3, length), np.float32), np.empty((0, length), np.float32)
    for r in range(rows.shape[0]):
        x = rows[r : r + 1]
        row_logit(x, w1, b1, w2, b2, w3, b3, wl, bl, z, a, pooled)
        g = dlogits[r]
        gbl[0] += g
        for c in range(3):
            for j in range(n):
                gl[c * n + j] += g * pooled[c, j]
                d[c, 3 * j : 3 * j + 3] = g * wl[c * n + j] * np.float32(1 / 3)
            d[c, 3 * n :] = 0  # the features average pooling leaves out
        leaky_backward(d, z[2], length)
        conv_backward(d, a[1], w3, g3, gb3, e, length)
        leaky_backward(e, z[1], length)
        conv_backward(e, a[0], w2, g2, gb2, d, length)
        leaky_backward(d, z[0], length)
        conv_backward(d, x, w1, g1, gb1, no_input, length)
    return g1, gb1, g2, gb2, g3, gb3, gl, gbl
