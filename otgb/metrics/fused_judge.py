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
        log_loss_gradients(arrays[0], np.zeros(1, np.float32), np.zeros(1, np.int64), *arrays[1:])
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


def set_log_loss_gradients(rows: Tensor, labels: Tensor, batch: Tensor, parameters: Sequence[Tensor]) -> None:
    """Sets each parameter's ``.grad`` to the gradient of the mean binary cross-entropy of ``PaperConvNet``'s logits of
    ``rows[batch]`` (rows: (N, L)) against ``labels[batch]`` (labels: (N,), 0 or 1): what autograd's forward and
    backward give, in one pass, with the rows read in place."""
    arrays = _arrays(rows, tuple(parameters))
    labels_, batch_ = labels.detach().to(torch.float32).contiguous().numpy(), batch.detach().contiguous().numpy()
    grads = log_loss_gradients(arrays[0], labels_, batch_, *arrays[1:])
    for parameter, grad in zip(parameters, grads):
        parameter.grad = torch.from_numpy(grad).reshape(parameter.shape)


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


@njit(inline="always")
def nine(w, o):
    """The nine weights of output channel o of a (3, 3, 3) kernel, input channel by input channel, as scalars (which
    the loops hold in registers)."""
    return w[o, 0, 0], w[o, 0, 1], w[o, 0, 2], w[o, 1, 0], w[o, 1, 1], w[o, 1, 2], w[o, 2, 0], w[o, 2, 1], w[o, 2, 2]


@njit(inline="always", fastmath=FAST)
def conv_from_one(src, w, b, a, length):
    """The first layer: a[:, 1:-1] = LeakyReLU(conv(src)) of one padded channel (1, L + 2) into three (3, L + 2)."""
    s, a0, a1, a2, slope = src[0], a[0], a[1], a[2], np.float32(SLOPE)
    w00, w01, w02 = w[0, 0, 0], w[0, 0, 1], w[0, 0, 2]
    w10, w11, w12 = w[1, 0, 0], w[1, 0, 1], w[1, 0, 2]
    w20, w21, w22 = w[2, 0, 0], w[2, 0, 1], w[2, 0, 2]
    b0, b1, b2 = b[0], b[1], b[2]
    for i in range(length):
        p0, p1, p2 = s[i], s[i + 1], s[i + 2]
        v0, v1, v2 = b0 + w00 * p0 + w01 * p1 + w02 * p2, b1 + w10 * p0 + w11 * p1 + w12 * p2, b2 + w20 * p0 + w21 * p1 + w22 * p2
        a0[i + 1] = v0 if v0 > 0 else v0 * slope
        a1[i + 1] = v1 if v1 > 0 else v1 * slope
        a2[i + 1] = v2 if v2 > 0 else v2 * slope


@njit(inline="always", fastmath=FAST)
def conv_from_three(src, w, b, a, length):
    """The second and third layers: as :func:`conv_from_one`, from three padded channels; the three outputs in one pass,
    so each input value is read once for the nine products it enters."""
    s0, s1, s2, a0, a1, a2, slope = src[0], src[1], src[2], a[0], a[1], a[2], np.float32(SLOPE)
    w000, w001, w002, w010, w011, w012, w020, w021, w022 = nine(w, 0)
    w100, w101, w102, w110, w111, w112, w120, w121, w122 = nine(w, 1)
    w200, w201, w202, w210, w211, w212, w220, w221, w222 = nine(w, 2)
    b0, b1, b2 = b[0], b[1], b[2]
    for i in range(length):
        p0, p1, p2, q0, q1, q2, r0, r1, r2 = s0[i], s0[i + 1], s0[i + 2], s1[i], s1[i + 1], s1[i + 2], s2[i], s2[i + 1], s2[i + 2]
        v0 = b0 + w000 * p0 + w001 * p1 + w002 * p2 + w010 * q0 + w011 * q1 + w012 * q2 + w020 * r0 + w021 * r1 + w022 * r2
        v1 = b1 + w100 * p0 + w101 * p1 + w102 * p2 + w110 * q0 + w111 * q1 + w112 * q2 + w120 * r0 + w121 * r1 + w122 * r2
        v2 = b2 + w200 * p0 + w201 * p1 + w202 * p2 + w210 * q0 + w211 * q1 + w212 * q2 + w220 * r0 + w221 * r1 + w222 * r2
        a0[i + 1] = v0 if v0 > 0 else v0 * slope
        a1[i + 1] = v1 if v1 > 0 else v1 * slope
        a2[i + 1] = v2 if v2 > 0 else v2 * slope


@njit(inline="always", fastmath=FAST)
def row_logit(row, w1, b1, w2, b2, w3, b3, wl, bl, padded_row, a, pooled):
    """One row's logit; leaves its padded activations a (3 layers, 3, L + 2) and pooled values. An activation has its
    pre-activation's sign (LeakyReLU's slope is positive), which is all the backward pass needs of the latter."""
    length, n = row.shape[0], row.shape[0] // 3
    padded_row[0, 1 : length + 1] = row
    conv_from_one(padded_row, w1, b1, a[0], length)
    conv_from_three(a[0], w2, b2, a[1], length)
    conv_from_three(a[1], w3, b3, a[2], length)
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
    """Adds a layer's weight and bias gradients from dz (its pre-activations' gradient, padded) and its padded input:
    one pass per input channel, which reads each of its values once for the nine weights it enters."""
    d0, d1, d2 = dz[0], dz[1], dz[2]
    t0, t1, t2 = np.float32(0), np.float32(0), np.float32(0)
    for i in range(1, length + 1):
        t0 += d0[i]
        t1 += d1[i]
        t2 += d2[i]
    db[0] += t0
    db[1] += t1
    db[2] += t2
    for c in range(src.shape[0]):
        s = src[c]
        g00, g01, g02, g10, g11, g12 = np.float32(0), np.float32(0), np.float32(0), np.float32(0), np.float32(0), np.float32(0)
        g20, g21, g22 = np.float32(0), np.float32(0), np.float32(0)
        for i in range(length):
            e0, e1, e2, p0, p1, p2 = d0[i + 1], d1[i + 1], d2[i + 1], s[i], s[i + 1], s[i + 2]
            g00 += e0 * p0
            g01 += e0 * p1
            g02 += e0 * p2
            g10 += e1 * p0
            g11 += e1 * p1
            g12 += e1 * p2
            g20 += e2 * p0
            g21 += e2 * p1
            g22 += e2 * p2
        dw[0, c, 0] += g00
        dw[0, c, 1] += g01
        dw[0, c, 2] += g02
        dw[1, c, 0] += g10
        dw[1, c, 1] += g11
        dw[1, c, 2] += g12
        dw[2, c, 0] += g20
        dw[2, c, 1] += g21
        dw[2, c, 2] += g22


@njit(inline="always", fastmath=FAST)
def input_gradient(dz, w, a_below, out, length):
    """The gradient of the layer below's pre-activations: the transposed convolution of dz, times LeakyReLU' (read from
    the sign of the layer's padded activations a_below); the three channels in one pass over dz."""
    d0, d1, d2, slope = dz[0], dz[1], dz[2], np.float32(SLOPE)
    c0, c1, c2, o0, o1, o2 = a_below[0], a_below[1], a_below[2], out[0], out[1], out[2]
    w000, w001, w002, w010, w011, w012, w020, w021, w022 = nine(w, 0)
    w100, w101, w102, w110, w111, w112, w120, w121, w122 = nine(w, 1)
    w200, w201, w202, w210, w211, w212, w220, w221, w222 = nine(w, 2)
    for i in range(length):
        e0, e1, e2, f0, f1, f2, h0, h1, h2 = d0[i + 2], d0[i + 1], d0[i], d1[i + 2], d1[i + 1], d1[i], d2[i + 2], d2[i + 1], d2[i]
        v0 = w000 * e0 + w001 * e1 + w002 * e2 + w100 * f0 + w101 * f1 + w102 * f2 + w200 * h0 + w201 * h1 + w202 * h2
        v1 = w010 * e0 + w011 * e1 + w012 * e2 + w110 * f0 + w111 * f1 + w112 * f2 + w210 * h0 + w211 * h1 + w212 * h2
        v2 = w020 * e0 + w021 * e1 + w022 * e2 + w120 * f0 + w121 * f1 + w122 * f2 + w220 * h0 + w221 * h1 + w222 * h2
        o0[i + 1] = v0 if c0[i + 1] > 0 else v0 * slope
        o1[i + 1] = v1 if c1[i + 1] > 0 else v1 * slope
        o2[i + 1] = v2 if c2[i + 1] > 0 else v2 * slope


@njit(nogil=True, cache=True, fastmath=FAST)
def logits(rows, w1, b1, w2, b2, w3, b3, wl, bl):
    length = rows.shape[1]
    padded_row, a = np.zeros((1, length + 2), np.float32), np.zeros((3, 3, length + 2), np.float32)
    pooled = np.empty((3, length // 3), np.float32)
    out = np.empty(rows.shape[0], np.float32)
    for r in range(rows.shape[0]):
        out[r] = row_logit(rows[r], w1, b1, w2, b2, w3, b3, wl, bl, padded_row, a, pooled)
    return out


@njit(inline="always", fastmath=FAST)
def add_row_gradients(g, w2, w3, wl, padded_row, a, pooled, d, e, grads, length):
    """Adds to ``grads`` (g1, gb1, g2, gb2, g3, gb3, gl, gbl) the gradients of ``g`` times the logit of the row whose
    forward pass :func:`row_logit` left in padded_row, a and pooled; d and e are padded work buffers."""
    g1, gb1, g2, gb2, g3, gb3, gl, gbl = grads
    n = length // 3
    gbl[0] += g
    for c in range(3):
        top, dc = a[2, c], d[c]
        for j in range(n):
            gl[c * n + j] += g * pooled[c, j]
            v = g * wl[c * n + j] * np.float32(1 / 3)
            for k in range(1, 4):
                dc[3 * j + k] = v if top[3 * j + k] > 0 else v * np.float32(SLOPE)
        for i in range(3 * n, length):  # the features average pooling leaves out
            dc[i + 1] = 0
    add_weight_gradients(d, a[1], g3, gb3, length)
    input_gradient(d, w3, a[1], e, length)
    add_weight_gradients(e, a[0], g2, gb2, length)
    input_gradient(e, w2, a[0], d, length)
    add_weight_gradients(d, padded_row, g1, gb1, length)


@njit(inline="always")
def buffers(length, w1, b1, w2, b2, w3, b3, wl, bl):
    """Zeroed gradients of the parameters, and a row's padded input, activations, pooled values and two work buffers
    (their padding stays 0)."""
    grads = (np.zeros_like(w1), np.zeros_like(b1), np.zeros_like(w2), np.zeros_like(b2), np.zeros_like(w3),
             np.zeros_like(b3), np.zeros_like(wl), np.zeros_like(bl))  # fmt: skip
    padded_row, a = np.zeros((1, length + 2), np.float32), np.zeros((3, 3, length + 2), np.float32)
    work = (np.zeros((3, length + 2), np.float32), np.zeros((3, length + 2), np.float32))
    return grads, padded_row, a, np.empty((3, length // 3), np.float32), work


@njit(nogil=True, cache=True, fastmath=FAST)
def gradients(rows, dlogits, w1, b1, w2, b2, w3, b3, wl, bl):
    """The parameters' gradients of sum_r dlogits[r] * logit(rows[r])."""
    length = rows.shape[1]
    grads, padded_row, a, pooled, (d, e) = buffers(length, w1, b1, w2, b2, w3, b3, wl, bl)
    for r in range(rows.shape[0]):
        row_logit(rows[r], w1, b1, w2, b2, w3, b3, wl, bl, padded_row, a, pooled)
        add_row_gradients(dlogits[r], w2, w3, wl, padded_row, a, pooled, d, e, grads, length)
    return grads


@njit(nogil=True, cache=True, fastmath=FAST)
def log_loss_gradients(rows, labels, batch, w1, b1, w2, b2, w3, b3, wl, bl):
    """The parameter gradients of the mean binary cross-entropy of the logits of rows[batch] against labels[batch]
    (0 or 1), in one pass: a row's share, (sigmoid(logit) - label) / batch size, is known as soon as its logit is, so
    one forward pass serves both (a step on autograd runs it twice: for the loss, and again inside the backward)."""
    length, count = rows.shape[1], batch.shape[0]
    grads, padded_row, a, pooled, (d, e) = buffers(length, w1, b1, w2, b2, w3, b3, wl, bl)
    for r in batch:
        logit = row_logit(rows[r], w1, b1, w2, b2, w3, b3, wl, bl, padded_row, a, pooled)
        probability = 1 / (1 + np.exp(-logit)) if logit >= 0 else np.exp(logit) / (1 + np.exp(logit))
        add_row_gradients(np.float32((probability - labels[r]) / count), w2, w3, wl, padded_row, a, pooled, d, e, grads, length)
    return grads
