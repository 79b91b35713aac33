"""The warm-start network's forward pass for inference (:class:`torchrod.learn.network.WarmStartNet`): a batch
of readings in, for each possible count h = 1..H the count's probability and h forces out, in SI units.

The network is trained and differentiated in torch; this is the same function, written once as kernel source for
the estimator's CPU path (compiled by :func:`torchrod.kernels.targets.cpu_network`, runnable as Python), and held to
the torch module by tests. At a batch of one reading, the torch pass costs far more than its arithmetic: each of its
few hundred small operations goes through torch's dispatch, whose code has left the processor's caches by the next
reading of a live source. Here a reading is one loop over a few arrays.

Each reading is computed on its own, so its guesses do not depend on the batch it comes in. The layers' products and
sums are float32, as in the trained network, in a fixed order; everything around them (the canonical frame, the
features, the layer norms, the heads) is float64. The outputs agree with the torch pass to float32 rounding.

Parameters (:func:`torchrod.kernels.host.network_rows` packs them): ``params`` float32, every layer's weights
transposed to (in, out) and its bias, gain and shift; ``layers`` (D + 1, 6) int64, each layer's (inputs, outputs,
weights, bias, gain, shift) offsets into ``params`` (gain -1 for the output layer: no norm, no activation);
``scales`` (4,) float64: the curvature scale, the force scale, the squared mean grating spacing (s / L), the layer
norms' epsilon; ``stencil`` (G - 2, 3) float64, the three-point second-derivative weights.
"""

import math

MIN_GAP = 1e-3
"""Least gap between guessed locations, and between them and the rod's ends, as a fraction of the length."""

RMS_FLOOR = 1e-3
"""The reading's RMS (dimensionless) is taken at least this share of the curvature scale."""


INLINE = ("wide",)
"""Small functions the CUDA target inlines where they are called (:func:`.targets.cuda_namespace`)."""


def wide(x):
    """A float32 number as a float64, alike in Python and compiled (Numba's ``float()`` keeps a float32 one)."""
    return 0.0 + float(x)


def network_rows(u, present, length, force_si, params, layers, H, scales, stencil, probs, s_out, f_out, xc, frame, a,
                 b):  # fmt: skip
    """The guesses of every reading r of u (B, G, 2) [1/m] and present (B, G): probs (B, H), s_out (B, H, H) [m]
    (count h's locations in ``[r, h - 1, :h]``, increasing), f_out (B, H, H, 2) [N]. ``length`` [m], ``force_si``
    EI / L^2 [N]. Scratch: xc (G, 2) and frame (R, 4) float64, a and b (R, widest layer) float32: the readings go
    through the layers R at a time, so that each layer's weights are read once for R readings (each reading's own
    arithmetic, and so its guesses, are the same in any block)."""
    B = u.shape[0]
    R = a.shape[0]
    for r0 in range(0, B, R):
        n = min(R, B - r0)
        for t in range(n):
            canonical(u[r0 + t], present[r0 + t], length, scales, stencil, xc, frame[t], a[t])
        layer_pass(params, layers, scales[3], n, a, b)
        raw = a if layers.shape[0] % 2 == 0 else b
        for t in range(n):
            f = frame[t]
            heads(raw[t], H, length, force_si, f[3] * (scales[1] / scales[0]), f[0], f[1], f[2], probs[r0 + t],
                  s_out[r0 + t], f_out[r0 + t])  # fmt: skip


def canonical(u, present, length, scales, stencil, xc, frame, a):
    """One reading (u (G, 2) [1/m], present (G,)) in its canonical frame: the turn p - iq that takes its largest read
    curvature to +x (the first of equals), then the sign of a reflection that makes the sum of u_y over the gratings
    non-negative; frame = (p, q, sign, rms), the RMS of u L over the read gratings; the network's input into ``a``
    (:func:`features`)."""
    G = u.shape[0]
    best = -1.0
    top = -1
    for k in range(G):
        if present[k]:
            x = u[k, 0] * length
            y = u[k, 1] * length
            m = math.sqrt(x * x + y * y)  # (not hypot: Python's and the compiled one round differently)
            if m > best:
                best = m
                top = k
    p = 1.0
    q = 0.0
    if top >= 0 and best > 0.0:
        p = u[top, 0] * length / best
        q = u[top, 1] * length / best
    total = 0.0
    count = 0
    for k in range(G):
        if present[k]:
            x = u[k, 0] * length
            y = u[k, 1] * length
            xc[k, 0] = x * p + y * q
            xc[k, 1] = y * p - x * q
            total += xc[k, 1]
            count += 1
        else:
            xc[k, 0] = 0.0
            xc[k, 1] = 0.0
    sign = 1.0 if total >= 0.0 else -1.0
    ss = 0.0
    for k in range(G):
        xc[k, 1] *= sign
        ss += xc[k, 0] * xc[k, 0] + xc[k, 1] * xc[k, 1]
    rms = math.sqrt(ss / (count if count > 0 else 1))
    if rms < RMS_FLOOR * scales[0]:
        rms = RMS_FLOOR * scales[0]
    frame[0] = p
    frame[1] = q
    frame[2] = sign
    frame[3] = rms
    features(present, G, rms, scales, stencil, xc, a)


def features(present, G, rms, scales, stencil, xc, a):
    """The network's input into ``a``: the reading in its frame divided by its RMS (2G), the mask (G), the log of
    the RMS over the curvature scale (1), and for G >= 3 the load density the reading implies at the interior
    gratings, r = U'' + |U|^2 U / 2 times h^2 / rms (2 (G - 2)), with where it is defined (G - 2)."""
    for k in range(G):
        a[2 * k] = xc[k, 0] / rms
        a[2 * k + 1] = xc[k, 1] / rms
        a[2 * G + k] = 1.0 if present[k] else 0.0
    a[3 * G] = math.log(rms / scales[0])
    if G >= 3:
        scale = scales[2] / rms
        at = 3 * G + 1
        for k in range(G - 2):
            valid = 1.0 if (present[k] and present[k + 1] and present[k + 2]) else 0.0
            mid2 = xc[k + 1, 0] * xc[k + 1, 0] + xc[k + 1, 1] * xc[k + 1, 1]
            for c in range(2):
                second = stencil[k, 0] * xc[k, c] + stencil[k, 1] * xc[k + 1, c] + stencil[k, 2] * xc[k + 2, c]
                a[at + 2 * k + c] = (second + 0.5 * mid2 * xc[k + 1, c]) * valid * scale
            a[at + 2 * (G - 2) + k] = valid


def layer_pass(params, layers, eps, n, a, b):
    """The layers of the readings in rows 0..n-1 of ``a`` (their input), alternating between ``a`` and ``b`` (the
    last layer's output lands in ``b`` for an odd number of layers, else in ``a``); ``eps`` the layer norms'
    epsilon."""
    src = a
    dst = b
    for layer in range(layers.shape[0]):
        n_in = layers[layer, 0]
        n_out = layers[layer, 1]
        w = layers[layer, 2]
        bias = params[layers[layer, 3] : layers[layer, 3] + n_out]
        for t in range(n):
            for j in range(n_out):
                dst[t, j] = 0.0
        # Eight inputs at a time: each output takes their eight products one after another, in the order of one
        # input at a time (the same rounding), loaded and stored once for the eight. (Views: the loops over j are
        # then vectorised.)
        i = 0
        while i + 8 <= n_in:
            r0 = params[w + i * n_out : w + (i + 1) * n_out]
            r1 = params[w + (i + 1) * n_out : w + (i + 2) * n_out]
            r2 = params[w + (i + 2) * n_out : w + (i + 3) * n_out]
            r3 = params[w + (i + 3) * n_out : w + (i + 4) * n_out]
            r4 = params[w + (i + 4) * n_out : w + (i + 5) * n_out]
            r5 = params[w + (i + 5) * n_out : w + (i + 6) * n_out]
            r6 = params[w + (i + 6) * n_out : w + (i + 7) * n_out]
            r7 = params[w + (i + 7) * n_out : w + (i + 8) * n_out]
            for t in range(n):
                x0 = src[t, i]
                x1 = src[t, i + 1]
                x2 = src[t, i + 2]
                x3 = src[t, i + 3]
                x4 = src[t, i + 4]
                x5 = src[t, i + 5]
                x6 = src[t, i + 6]
                x7 = src[t, i + 7]
                y = dst[t]
                for j in range(n_out):
                    v = y[j]
                    v += x0 * r0[j]
                    v += x1 * r1[j]
                    v += x2 * r2[j]
                    v += x3 * r3[j]
                    v += x4 * r4[j]
                    v += x5 * r5[j]
                    v += x6 * r6[j]
                    v += x7 * r7[j]
                    y[j] = v
            i += 8
        while i < n_in:
            row = params[w + i * n_out : w + (i + 1) * n_out]
            for t in range(n):
                x = src[t, i]
                y = dst[t]
                for j in range(n_out):
                    y[j] += x * row[j]
            i += 1
        for t in range(n):
            for j in range(n_out):
                dst[t, j] += bias[j]
            if layers[layer, 4] >= 0:
                norm_silu(params, layers[layer, 4], layers[layer, 5], eps, n_out, dst[t])
        src, dst = dst, src


def norm_silu(params, gain, shift, eps, n, y):
    """Layer norm (biased variance, ``eps`` added to it; gain and shift at those offsets of ``params``) then SiLU,
    of y (n,) in place."""
    mean = 0.0
    for j in range(n):
        mean += wide(y[j])
    mean /= n
    var = 0.0
    for j in range(n):
        d = wide(y[j]) - mean
        var += d * d
    var /= n
    inv = 1.0 / math.sqrt(var + eps)
    for j in range(n):
        v = (wide(y[j]) - mean) * inv * wide(params[gain + j]) + wide(params[shift + j])
        y[j] = v / (1.0 + math.exp(-v)) if v > -700.0 else 0.0  # (exp would overflow: SiLU is 0 there)


def heads(raw, H, length, force_si, force_unit, p, q, sign, probs, s_out, f_out):
    """The count probabilities (softmax of the first H outputs) and, for each count h, its h locations (cumulative
    sums of a softmax over h + 1 gaps, each at least ``MIN_GAP``) and forces (multiples of ``force_unit``, turned back
    to the reading's frame), in SI units."""
    top = wide(raw[0])
    for h in range(1, H):
        if wide(raw[h]) > top:
            top = wide(raw[h])
    total = 0.0
    for h in range(H):
        probs[h] = math.exp(wide(raw[h]) - top)
        total += probs[h]
    for h in range(H):
        probs[h] /= total
    start = H
    for h in range(1, H + 1):
        top = wide(raw[start])
        for j in range(1, h + 1):
            if wide(raw[start + j]) > top:
                top = wide(raw[start + j])
        total = 0.0
        for j in range(h + 1):
            total += math.exp(wide(raw[start + j]) - top)
        share = 1.0 - (h + 1) * MIN_GAP
        cum = 0.0
        for j in range(H):
            if j < h:
                cum += MIN_GAP + share * (math.exp(wide(raw[start + j]) - top) / total)
                s_out[h - 1, j] = cum * length
                fx = wide(raw[start + h + 1 + 2 * j]) * force_unit * sign
                fy = wide(raw[start + h + 2 + 2 * j]) * force_unit
                f_out[h - 1, j, 0] = (fx * p - fy * q) * force_si
                f_out[h - 1, j, 1] = (fx * q + fy * p) * force_si
            else:
                s_out[h - 1, j] = math.nan
                f_out[h - 1, j, 0] = math.nan
                f_out[h - 1, j, 1] = math.nan
        start += (h + 1) + 2 * h
