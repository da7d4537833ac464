"""Image metrics and the 3DGS photometric training loss, in MLX.

Images are MLX arrays of shape ``(H, W, C)`` (usually ``C = 3``, sRGB in
``[0, 1]``, row 0 at the top); any leading batch axes ``(..., H, W, C)`` are
also accepted and are reduced together with the pixels.  Every function is
built from differentiable MLX ops, so ``mx.grad`` works through all of them
(with respect to both ``img`` and ``ref``).

Masks
-----
``mask`` is an optional per-pixel weight of shape ``(H, W)`` (or anything that
broadcasts against the image without its channel axis, e.g. ``(..., H, W)``);
booleans are read as 0/1.  A masked metric is the *weighted mean* of the
per-pixel quantity (averaged over channels first)::

    metric = sum(w * q) / sum(w)

so with a 0/1 mask, L1 and PSNR equal the same metric computed on the kept
pixels only.  For SSIM the mask weights the SSIM *map*: the local statistics
are still computed on the full image (pixels outside the mask do contribute
to the windows around kept pixels near the mask border), and the map is then
averaged with the weights.  A mask whose weights sum to 0 gives 0 for the
weighted means (L1 = 0, SSIM = 0) and the PSNR cap below.

SSIM
----
The structural similarity of Wang et al. (2004) exactly as computed by the
3DGS reference training code (``utils/loss_utils.py::ssim``): an 11x11
Gaussian window with sigma 1.5 normalised to sum 1, ``C1 = 0.01**2``,
``C2 = 0.03**2`` (data range 1), statistics per channel with a zero-padded
"same"-size convolution (``F.conv2d(..., padding=window // 2)``), and the
map averaged over channels and pixels.

The Gaussian filter is applied as two separable 1-D passes written as a sum
of shifted slices of the zero-padded image (the kernel is symmetric, so
pairs of taps share one multiply).  On MLX's CPU backend this measured about
2x faster than depthwise ``mx.conv2d``/``conv1d`` and 10x faster than the
full 11x11 kernel.  The pass carries a custom VJP: a zero-padded "same"
convolution with a symmetric kernel is a symmetric linear operator, so its
VJP is the same filter applied to the cotangent, which is much cheaper than
differentiating through the slices.  The hot paths are ``mx.compile``-d
(``compiled=False`` gives the plain graph; both agree to float32 rounding).
"""

from __future__ import annotations

import functools
import math
from typing import Callable, Optional, Tuple

import mlx.core as mx
import numpy as np

__all__ = [
    "SSIM_C1",
    "SSIM_C2",
    "PSNR_MAX_DB",
    "gaussian_window",
    "mse",
    "l1",
    "psnr",
    "ssim_map",
    "ssim",
    "photometric_loss",
]

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2

# PSNR of identical images would be +inf; the MSE is floored at 1e-10 instead,
# which caps PSNR at 100 dB (for data range 1) and keeps it finite.
_MSE_FLOOR = 1e-10
PSNR_MAX_DB = -10.0 * math.log10(_MSE_FLOOR)

# Smallest total mask weight used as a divisor (an all-zero mask gives 0).
_WEIGHT_FLOOR = 1e-12


# ----------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------


def gaussian_window(window: int = 11, sigma: float = 1.5) -> np.ndarray:
    """The normalised 1-D Gaussian of 3DGS's ``gaussian(window_size, sigma)``.

    ``g[x] = exp(-(x - window // 2)**2 / (2 sigma**2)) / sum``, ``x = 0 ..
    window - 1``; the 2-D SSIM window is ``outer(g, g)``.  Returned as float64.
    """
    window = int(window)
    if window < 1 or window % 2 == 0:
        raise ValueError(f"SSIM window must be a positive odd size, got {window}")
    if not sigma > 0:
        raise ValueError(f"SSIM sigma must be > 0, got {sigma}")
    x = np.arange(window, dtype=np.float64) - window // 2
    g = np.exp(-(x * x) / (2.0 * float(sigma) ** 2))
    return g / g.sum()


def _check_pair(img: mx.array, ref: mx.array, name: str) -> None:
    if img.ndim < 3:
        raise ValueError(f"{name}: images must be (..., H, W, C), got shape {img.shape}")
    if img.shape != ref.shape:
        raise ValueError(f"{name}: image shapes differ: {img.shape} vs {ref.shape}")


def _as_weights(mask, img: mx.array, name: str) -> mx.array:
    """Mask -> float32 weights broadcastable to the image's (..., H, W)."""
    w = mask if isinstance(mask, mx.array) else mx.array(np.asarray(mask))
    if w.dtype != img.dtype:
        w = w.astype(img.dtype)
    pix = tuple(img.shape[:-1])
    try:
        ok = np.broadcast_shapes(tuple(w.shape), pix) == pix
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(
            f"{name}: mask of shape {w.shape} does not broadcast to the image "
            f"pixels {img.shape[:-1]}"
        )
    return w


def _weighted_mean(q: mx.array, w: Optional[mx.array]) -> mx.array:
    """Mean of the per-pixel map ``q`` (..., H, W), optionally weighted."""
    if w is None:
        return mx.mean(q)
    w = mx.broadcast_to(w, q.shape)
    return mx.sum(q * w) / mx.maximum(mx.sum(w), _WEIGHT_FLOOR)


# ----------------------------------------------------------------------------
# separable Gaussian filter
# ----------------------------------------------------------------------------


def _filter_axis(x: mx.array, taps: Tuple[float, ...], axis: int) -> mx.array:
    """Zero-padded "same" correlation of ``x`` with the symmetric ``taps``."""
    r = len(taps) // 2
    n = x.shape[axis]
    if r == 0:
        return taps[0] * x
    pads = [(0, 0)] * x.ndim
    pads[axis] = (r, r)
    p = mx.pad(x, pads)

    def shifted(k: int) -> mx.array:
        idx = [slice(None)] * x.ndim
        idx[axis] = slice(k, k + n)
        return p[tuple(idx)]

    y = taps[r] * shifted(r)
    for k in range(r):  # taps[k] == taps[2r - k]
        y = y + taps[k] * (shifted(k) + shifted(2 * r - k))
    return y


def _separable(x: mx.array, taps: Tuple[float, ...]) -> mx.array:
    """The 2-D filter ``outer(taps, taps)`` over axes (-3, -2) of (..., H, W, C)."""
    return _filter_axis(_filter_axis(x, taps, x.ndim - 3), taps, x.ndim - 2)


def _taps(window: int, sigma: float) -> Tuple[float, ...]:
    return tuple(float(t) for t in gaussian_window(window, sigma).astype(np.float32))


@functools.lru_cache(maxsize=None)
def _gaussian_blur(window: int, sigma: float) -> Callable[[mx.array], mx.array]:
    """Separable Gaussian filter with a self-adjoint VJP (plain, uncompiled)."""
    taps = _taps(window, sigma)

    @mx.custom_function
    def filt(x):
        return _separable(x, taps)

    @filt.vjp
    def filt_vjp(primals, cotangent, output):
        # Symmetric kernel + zero padding: the operator is its own transpose.
        return _separable(cotangent, taps)

    return filt


# ----------------------------------------------------------------------------
# SSIM
# ----------------------------------------------------------------------------


def _ssim_map_plain(img: mx.array, ref: mx.array, window: int, sigma: float) -> mx.array:
    """Per-channel SSIM map (..., H, W, C) as a plain MLX graph (autograd VJP)."""
    blur = _gaussian_blur(window, sigma)
    mu1 = blur(img)
    mu2 = blur(ref)
    mu1_mu2 = mu1 * mu2
    mu1_sq = mu1 * mu1
    mu2_sq = mu2 * mu2
    sigma1_sq = blur(img * img) - mu1_sq
    sigma2_sq = blur(ref * ref) - mu2_sq
    sigma12 = blur(img * ref) - mu1_mu2
    num = (2.0 * mu1_mu2 + SSIM_C1) * (2.0 * sigma12 + SSIM_C2)
    den = (mu1_sq + mu2_sq + SSIM_C1) * (sigma1_sq + sigma2_sq + SSIM_C2)
    return num / den


@functools.lru_cache(maxsize=None)
def _ssim_map_fused(window: int, sigma: float) -> Callable[[mx.array, mx.array], mx.array]:
    """Per-channel SSIM map with a compiled forward and a closed-form VJP.

    With ``A1 = 2 mu1 mu2 + C1``, ``A2 = 2 s12 + C2``, ``B1 = mu1^2 + mu2^2 +
    C1``, ``B2 = s11 + s22 + C2`` and ``S = A1 A2 / (B1 B2)``, the partials of
    ``S`` with respect to the filtered moments are

    * ``dS/d mu1  = (2 mu2 (A2 - A1) - 2 mu1 S (B2 - B1)) / (B1 B2)`` (and
      symmetrically for ``mu2``),
    * ``dS/d E[x^2] = dS/d E[y^2] = -S / B2``,
    * ``dS/d E[xy] = 2 A1 / (B1 B2)``.

    The forward pass stores them next to the map; the VJP filters the
    cotangent-weighted partials (the filter is self-adjoint) and applies the
    chain rule through ``x``, ``x^2`` and ``x y``: three filter passes for the
    gradient of ``img``, one more for ``ref``.
    """
    taps = _taps(window, sigma)

    def blur(x):
        return _separable(x, taps)

    def forward(x, y):
        mu1 = blur(x)
        mu2 = blur(y)
        mu1_mu2 = mu1 * mu2
        mu1_sq = mu1 * mu1
        mu2_sq = mu2 * mu2
        a1 = 2.0 * mu1_mu2 + SSIM_C1
        a2 = 2.0 * (blur(x * y) - mu1_mu2) + SSIM_C2
        b1 = mu1_sq + mu2_sq + SSIM_C1
        b2 = (blur(x * x) - mu1_sq) + (blur(y * y) - mu2_sq) + SSIM_C2
        inv_den = 1.0 / (b1 * b2)
        smap = a1 * a2 * inv_den
        da = 2.0 * (a2 - a1) * inv_den
        db = 2.0 * smap * (b2 - b1) * inv_den
        p_mu1 = mu2 * da - mu1 * db
        p_mu2 = mu1 * da - mu2 * db
        p_sq = -smap / b2
        p_xy = 2.0 * a1 * inv_den
        return smap, p_mu1, p_mu2, p_sq, p_xy

    forward = mx.compile(forward)
    weighted_blur = mx.compile(lambda c, p: blur(c * p))
    chain = mx.compile(lambda c, p_mu, own, other, b_sq, b_xy: blur(c * p_mu) + 2.0 * own * b_sq + other * b_xy)

    @mx.custom_function
    def fused(x, y):
        return forward(x, y)

    @fused.vjp
    def fused_vjp(primals, cotangents, outputs):
        x, y = primals
        c = cotangents[0]  # only the map is differentiable
        _, p_mu1, p_mu2, p_sq, p_xy = outputs
        b_sq = weighted_blur(c, p_sq)
        b_xy = weighted_blur(c, p_xy)
        # Separate calls: lazy evaluation skips the ref gradient when unused.
        gx = chain(c, p_mu1, x, y, b_sq, b_xy)
        gy = chain(c, p_mu2, y, x, b_sq, b_xy)
        return gx, gy

    return lambda x, y: fused(x, y)[0]


def _ssim_map_impl(img: mx.array, ref: mx.array, window: int, sigma: float, compiled: bool) -> mx.array:
    """SSIM map averaged over channels: (..., H, W)."""
    if compiled:
        smap = _ssim_map_fused(window, sigma)(img, ref)
    else:
        smap = _ssim_map_plain(img, ref, window, sigma)
    return mx.mean(smap, axis=-1)


def _ssim_impl(img, ref, mask, window, sigma, compiled):
    return _weighted_mean(_ssim_map_impl(img, ref, window, sigma, compiled), mask)


def _l1_impl(img, ref, mask):
    return _weighted_mean(mx.mean(mx.abs(img - ref), axis=-1), mask)


def _mse_impl(img, ref, mask):
    d = img - ref
    return _weighted_mean(mx.mean(d * d, axis=-1), mask)


def _photometric_impl(img, ref, mask, lambda_dssim, window, sigma, compiled):
    loss = (1.0 - lambda_dssim) * _l1_impl(img, ref, mask)
    if lambda_dssim != 0.0:
        loss = loss + lambda_dssim * (1.0 - _ssim_impl(img, ref, mask, window, sigma, compiled))
    return loss


@functools.lru_cache(maxsize=None)
def _compiled(kind: str, has_mask: bool, *static) -> Callable:
    """One compiled graph per (function, mask or not, python constants)."""
    if kind == "ssim_map":
        window, sigma = static
        fn = lambda a, b: _ssim_map_impl(a, b, window, sigma, True)  # noqa: E731
    elif kind == "ssim":
        window, sigma = static
        if has_mask:
            fn = lambda a, b, w: _ssim_impl(a, b, w, window, sigma, True)  # noqa: E731
        else:
            fn = lambda a, b: _ssim_impl(a, b, None, window, sigma, True)  # noqa: E731
    elif kind == "photometric":
        lam, window, sigma = static
        if has_mask:
            fn = lambda a, b, w: _photometric_impl(a, b, w, lam, window, sigma, True)  # noqa: E731
        else:
            fn = lambda a, b: _photometric_impl(a, b, None, lam, window, sigma, True)  # noqa: E731
    else:  # pragma: no cover - internal
        raise KeyError(kind)
    return mx.compile(fn)


def _run(kind, img, ref, w, *static):
    fn = _compiled(kind, w is not None, *static)
    return fn(img, ref) if w is None else fn(img, ref, w)


# ----------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------


def l1(img: mx.array, ref: mx.array, mask=None) -> mx.array:
    """Mean absolute error (scalar); with ``mask``, the weighted mean over pixels."""
    _check_pair(img, ref, "l1")
    w = None if mask is None else _as_weights(mask, img, "l1")
    return _l1_impl(img, ref, w)


def mse(img: mx.array, ref: mx.array, mask=None) -> mx.array:
    """Mean squared error (scalar); with ``mask``, the weighted mean over pixels."""
    _check_pair(img, ref, "mse")
    w = None if mask is None else _as_weights(mask, img, "mse")
    return _mse_impl(img, ref, w)


def psnr(img: mx.array, ref: mx.array, mask=None) -> mx.array:
    """Peak signal-to-noise ratio in dB for data range 1: ``-10 log10(MSE)``.

    The MSE is averaged over channels and pixels (weighted by ``mask`` if
    given).  Identical images would give +inf; the MSE is floored at 1e-10, so
    the result is capped at :data:`PSNR_MAX_DB` (100 dB) and always finite.
    """
    m = mse(img, ref, mask)
    return -10.0 * mx.log10(mx.maximum(m, _MSE_FLOOR))


def ssim_map(
    img: mx.array,
    ref: mx.array,
    window: int = 11,
    sigma: float = 1.5,
    *,
    compiled: bool = True,
) -> mx.array:
    """Per-pixel SSIM (3DGS definition), averaged over channels: ``(..., H, W)``."""
    _check_pair(img, ref, "ssim_map")
    gaussian_window(window, sigma)  # validates
    if compiled:
        return _run("ssim_map", img, ref, None, int(window), float(sigma))
    return _ssim_map_impl(img, ref, int(window), float(sigma), False)


def ssim(
    img: mx.array,
    ref: mx.array,
    window: int = 11,
    sigma: float = 1.5,
    mask=None,
    *,
    compiled: bool = True,
) -> mx.array:
    """Mean SSIM (scalar), as 3DGS's ``ssim(img1, img2)``.

    With ``mask`` the SSIM map is averaged with those weights (see the module
    docstring: the local windows still see the whole image).
    """
    _check_pair(img, ref, "ssim")
    gaussian_window(window, sigma)
    w = None if mask is None else _as_weights(mask, img, "ssim")
    if compiled:
        return _run("ssim", img, ref, w, int(window), float(sigma))
    return _ssim_impl(img, ref, w, int(window), float(sigma), False)


def photometric_loss(
    img: mx.array,
    ref: mx.array,
    lambda_dssim: float = 0.2,
    mask=None,
    *,
    window: int = 11,
    sigma: float = 1.5,
    compiled: bool = True,
) -> mx.array:
    """The 3DGS training loss ``(1 - lambda) * L1 + lambda * (1 - SSIM)``.

    ``img`` is the render, ``ref`` the ground-truth photo; ``mask`` weights both
    terms as in :func:`l1` and :func:`ssim`.
    """
    _check_pair(img, ref, "photometric_loss")
    lam = float(lambda_dssim)
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lambda_dssim must be in [0, 1], got {lambda_dssim}")
    gaussian_window(window, sigma)
    w = None if mask is None else _as_weights(mask, img, "photometric_loss")
    if compiled:
        return _run("photometric", img, ref, w, lam, int(window), float(sigma))
    return _photometric_impl(img, ref, w, lam, int(window), float(sigma), False)
