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
import threading
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

log = logging.getLogger("otgb.metrics")

try:
    from numba import njit
except Exception as error:  # numba missing or broken on this platform: the torch path runs
    UNAVAILABLE = f"{type(error).__name__}: {error}"

    def njit(**options):  # the loops stay Python functions, never called
        return lambda function: function
else:
    UNAVAILABLE = ""

_state = {"why": f"numba did not import ({UNAVAILABLE})" if UNAVAILABLE else "", "said": False, "compiled": False}
_lock = threading.Lock()  # folds train in threads: one compiles, one says why


def available(rows: Tensor, parameters: Sequence[Tensor]) -> bool:
    """Whether the fused loops can run the network: float32 rows and parameters on the CPU, outside autocast, no gradient
    of the rows wanted, and :func:`usable`."""
    on_cpu = all(t.device.type == "cpu" and t.dtype == torch.float32 for t in (rows, *parameters))
    return on_cpu and not rows.requires_grad and not _autocast_on_cpu() and usable()


def usable() -> bool:
    """Whether numba imported and the loops compiled (at the first call; a failure is said once)."""
    with _lock:
        if not _state["why"] and not _state["compiled"]:
            _compile()
        if _state["why"] and not _state["said"]:
            log.warning(f"otgb: the paper's C2ST judge runs on torch's operations, slower: {_state['why']}")
            _state["said"] = True
    return not _state["why"]


def _autocast_on_cpu() -> bool:
    try:
        return torch.is_autocast_enabled("cpu")
    except TypeError:  # torch < 2.4
        return torch.is_autocast_cpu_enabled()


def _compile() -> None:
    """Compile (or load from numba's cache) both loops on a one-row network; a failure leaves the reason in ``_state``."""
    first, second, third = (np.zeros((3, channels, 3), np.float32) for channels in (1, 3, 3))
    bias, row = np.zeros(3, np.float32), np.zeros((1, 3), np.float32)
    arrays = [row, first, bias, second, bias, third, bias, np.zeros(3, np.float32), np.zeros(1, np.float32)]
    try:
        logits(*arrays)
        gradients(arrays[0], np.zeros(1, np.float32), *arrays[1:])
    except Exception as error:  # an unsupported CPU, an LLVM failure: the torch path runs
        _state["why"] = f"its loops did not compile ({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''})"
    else:
        _state["compiled"] = True


class FusedPaperConvNet(torch.autograd.Function):
    """``PaperConvNet``'s logits of ``rows`` (B, L) from its parameters; the backward gives the parameters' gradients."""

    @staticmethod
    def forward(ctx, rows: Tensor, *parameters: Tensor) -> Tensor:
        arrays = _arrays(rows, parameters)
        ctx.save_for_backward(rows, *parameters)
        return torch.from_numpy(logits(*arrays))

    @staticmethod
    @once_differentiable
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
# Activations and their gradients live in buffers padded by one zero at each end (the convolutions'
# zero padding), so every loop runs over the whole row with no bounds to test and vectorises.
FAST = {"reassoc", "contract", "nsz"}  # vectorised sums (another order of float32 additions), fused multiply-adds
SLOPE = 0.01  # LeakyReLU's default negative slope, as in PaperConvNet


@njit(inline="always", fastmath=FAST)
def conv_from_one(src, w, b, z, a, length):
    """The first layer: z = conv(src) of one padded channel (1, L + 2) into (3, L); a[:, 1:-1] = LeakyReLU(z)."""
    s = src[0]
    for o in range(3):
        w0, w1, w2, bias = w[o, 0, 0], w[o, 0, 1], w[o, 0, 2], b[o]
        zo, ao = z[o], a[o]
        for i in range(length):
            v = bias + w0 * s[i] + w1 * s[i + 1] + w2 * s[i + 2]
            zo[i] = v
            ao[i + 1] = v if v > 0 else v * np.float32(SLOPE)


@njit(inline="always", fastmath=FAST)
def conv_from_three(src, w, b, z, a, length):
    """The second and third layers: as :func:`conv_from_one`, from three padded channels."""
    s0, s1, s2 = src[0], src[1], src[2]
    for o in range(3):
        u0, u1, u2, v0, v1, v2 = w[o, 0, 0], w[o, 0, 1], w[o, 0, 2], w[o, 1, 0], w[o, 1, 1], w[o, 1, 2]
        x0, x1, x2, bias = w[o, 2, 0], w[o, 2, 1], w[o, 2, 2], b[o]
        zo, ao = z[o], a[o]
        for i in range(length):
            v = bias + u0 * s0[i] + u1 * s0[i + 1] + u2 * s0[i + 2] + v0 * s1[i] + v1 * s1[i + 1] + v2 * s1[i + 2]
            v += x0 * s2[i] + x1 * s2[i + 1] + x2 * s2[i + 2]
            zo[i] = v
            ao[i + 1] = v if v > 0 else v * np.float32(SLOPE)


@njit(inline="always", fastmath=FAST)
def row_logit(row, w1, b1, w2, b2, w3, b3, wl, bl, padded_row, z, a, pooled):
    """One row's logit; leaves its pre-activations z (3 layers, 3, L), padded activations a and pooled values."""
    length, n = row.shape[0], row.shape[0] // 3
    padded_row[0, 1 : length + 1] = row
    conv_from_one(padded_row, w1, b1, z[0], a[0], length)
    conv_from_three(a[0], w2, b2, z[1], a[1], length)
    conv_from_three(a[1], w3, b3, z[2], a[2], length)
    logit = bl[0]
    for c in range(3):
        last = a[2, c]
        for j in range(n):
            mean = (last[3 * j + 1] + last[3 * j + 2] + last[3 * j + 3]) * np.float32(1 / 3)
            pooled[c, j] = mean
            logit += wl[c * n + j] * mean
    return logit


@njit(inline="always", fastmath=FAST)
def add_weight_gradients(dz, src, dw, db, length):
    """Adds a layer's weight and bias gradients from dz (its pre-activations' gradient, padded) and its padded input."""
    for o in range(3):
        d = dz[o]
        total = np.float32(0)
        for i in range(1, length + 1):
            total += d[i]
        db[o] += total
        for c in range(src.shape[0]):
            s = src[c]
            g0, g1, g2 = np.float32(0), np.float32(0), np.float32(0)
            for i in range(length):
                di = d[i + 1]
                g0 += di * s[i]
                g1 += di * s[i + 1]
                g2 += di * s[i + 2]
            dw[o, c, 0] += g0
            dw[o, c, 1] += g1
            dw[o, c, 2] += g2


@njit(inline="always", fastmath=FAST)
def input_gradient(dz, w, z_below, out, length):
    """The gradient of the layer below's pre-activations z_below: the transposed convolution of dz, times LeakyReLU'."""
    d0, d1, d2 = dz[0], dz[1], dz[2]
    for c in range(3):
        u0, u1, u2, v0, v1, v2 = w[0, c, 0], w[0, c, 1], w[0, c, 2], w[1, c, 0], w[1, c, 1], w[1, c, 2]
        x0, x1, x2 = w[2, c, 0], w[2, c, 1], w[2, c, 2]
        zc, oc = z_below[c], out[c]
        for i in range(length):
            v = (
                u0 * d0[i + 2] + u1 * d0[i + 1] + u2 * d0[i]
                + v0 * d1[i + 2] + v1 * d1[i + 1] + v2 * d1[i]
                + x0 * d2[i + 2] + x1 * d2[i + 1] + x2 * d2[i]
            )  # fmt: skip
            oc[i + 1] = v if zc[i] > 0 else v * np.float32(SLOPE)


@njit(nogil=True, cache=True, fastmath=FAST)
def logits(rows, w1, b1, w2, b2, w3, b3, wl, bl):
    length = rows.shape[1]
    padded_row, a = np.zeros((1, length + 2), np.float32), np.zeros((3, 3, length + 2), np.float32)
    z, pooled = np.empty((3, 3, length), np.float32), np.empty((3, length // 3), np.float32)
    out = np.empty(rows.shape[0], np.float32)
    for r in range(rows.shape[0]):
        out[r] = row_logit(rows[r], w1, b1, w2, b2, w3, b3, wl, bl, padded_row, z, a, pooled)
    return out


@njit(nogil=True, cache=True, fastmath=FAST)
def gradients(rows, dlogits, w1, b1, w2, b2, w3, b3, wl, bl):
    length = rows.shape[1]
    n = length // 3
    g1, g2, g3 = np.zeros_like(w1), np.zeros_like(w2), np.zeros_like(w3)
    gb1, gb2, gb3 = np.zeros_like(b1), np.zeros_like(b2), np.zeros_like(b3)
    gl, gbl = np.zeros_like(wl), np.zeros_like(bl)
    padded_row, a = np.zeros((1, length + 2), np.float32), np.zeros((3, 3, length + 2), np.float32)
    z, pooled = np.empty((3, 3, length), np.float32), np.empty((3, n), np.float32)
    d, e = np.zeros((3, length + 2), np.float32), np.zeros((3, length + 2), np.float32)  # the padding stays 0
    for r in range(rows.shape[0]):
        row_logit(rows[r], w1, b1, w2, b2, w3, b3, wl, bl, padded_row, z, a, pooled)
        g = dlogits[r]
        gbl[0] += g
        for c in range(3):
            top, dc = z[2, c], d[c]
            for j in range(n):
                gl[c * n + j] += g * pooled[c, j]
                v = g * wl[c * n + j] * np.float32(1 / 3)
                for k in range(3):
                    dc[3 * j + k + 1] = v if top[3 * j + k] > 0 else v * np.float32(SLOPE)
            for i in range(3 * n, length):  # the features average pooling leaves out
                dc[i + 1] = 0
        add_weight_gradients(d, a[1], g3, gb3, length)
        input_gradient(d, w3, z[1], e, length)
        add_weight_gradients(e, a[0], g2, gb2, length)
        input_gradient(e, w2, z[0], d, length)
        add_weight_gradients(d, padded_row, g1, gb1, length)
    return g1, gb1, g2, gb2, g3, gb3, gl, gbl
