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

The Gaussian filter is applied as two separable 1-D passes written as sums
of shifted slices of the zero-padded image (padded once on both axes; the
kernel is symmetric, so pairs of taps share one multiply).  On MLX's CPU
backend (512x512, 15 channels) this took 120 ms uncompiled and 20 ms
compiled, against 270 ms for a depthwise ``mx.conv2d`` pair and 1.1 s for
the full 11x11 kernel.  The filter carries a custom VJP: a zero-padded
"same" convolution with a symmetric kernel is a symmetric linear operator,
so its VJP is the same filter applied to the cotangent, far cheaper than
differentiating through the slices.

Compilation
-----------
``ssim``, ``ssim_map`` and ``photometric_loss`` run ``mx.compile``-d graphs
(``compiled=False`` gives the plain graph; both agree to float32 rounding).
MLX bypasses compilation for arrays being traced by a transformation, so
inside ``mx.grad``/``mx.value_and_grad`` they run as the plain graph.  For
the training loss use :func:`photometric_loss_and_grad`, which compiles the
loss *and* its gradient with respect to the image as one graph (about 2x
faster than ``mx.value_and_grad(photometric_loss)``), and push the returned
gradient through the renderer, or compile the whole training step.

Large images allocate many temporaries and MLX's default buffer cache on
Linux is small (32 MB); raising it with ``mx.set_cache_limit`` saved 5-30%
at 512x512 in our measurements (a process-wide setting, left to the
application).
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
    "photometric_loss_and_grad",
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
    """Mask -> weights (image dtype) broadcastable to the image's (..., H, W)."""
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


def _taps(window: int, sigma: float) -> Tuple[float, ...]:
    return tuple(float(t) for t in gaussian_window(window, sigma).astype(np.float32))


def _filter_valid(p: mx.array, taps: Tuple[float, ...], axis: int, n: int) -> mx.array:
    """Valid (unpadded) correlation of ``p`` with symmetric ``taps`` along ``axis``.

    ``p`` is already padded by ``len(taps) // 2`` on that axis; the result has
    length ``n`` there.  Symmetric taps share one multiply per pair.
    """
    r = len(taps) // 2

    def shifted(k: int) -> mx.array:
        idx = [slice(None)] * p.ndim
        idx[axis] = slice(k, k + n)
        return p[tuple(idx)]

    y = taps[r] * shifted(r)
    for k in range(r):  # taps[k] == taps[2r - k]
        y = y + taps[k] * (shifted(k) + shifted(2 * r - k))
    return y


def _separable(x: mx.array, taps: Tuple[float, ...]) -> mx.array:
    """Zero-padded "same" filtering of (..., H, W, C) with ``outer(taps, taps)``.

    The image is padded once on both axes; the vertical pass keeps the padded
    columns (they stay zero) so the horizontal pass needs no second pad.
    """
    r = len(taps) // 2
    h, w = x.shape[-3], x.shape[-2]
    if r == 0:
        return (taps[0] * taps[0]) * x
    p = mx.pad(x, [(0, 0)] * (x.ndim - 3) + [(r, r), (r, r), (0, 0)])
    return _filter_valid(_filter_valid(p, taps, x.ndim - 3, h), taps, x.ndim - 2, w)


@functools.lru_cache(maxsize=None)
def _gaussian_blur(window: int, sigma: float) -> Callable[[mx.array], mx.array]:
    """Separable Gaussian filter over axes (-3, -2) with a self-adjoint VJP."""
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
# metric graphs
# ----------------------------------------------------------------------------


def _ssim_map_impl(img: mx.array, ref: mx.array, window: int, sigma: float) -> mx.array:
    """SSIM map averaged over channels: (..., H, W)."""
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
    return mx.mean(num / den, axis=-1)


def _ssim_impl(img, ref, mask, window, sigma):
    return _weighted_mean(_ssim_map_impl(img, ref, window, sigma), mask)


def _l1_impl(img, ref, mask):
    return _weighted_mean(mx.mean(mx.abs(img - ref), axis=-1), mask)


def _mse_impl(img, ref, mask):
    d = img - ref
    return _weighted_mean(mx.mean(d * d, axis=-1), mask)


def _photometric_impl(img, ref, mask, lambda_dssim, window, sigma):
    loss = (1.0 - lambda_dssim) * _l1_impl(img, ref, mask)
    if lambda_dssim != 0.0:
        loss = loss + lambda_dssim * (1.0 - _ssim_impl(img, ref, mask, window, sigma))
    return loss


def _bind(kind: str, static: tuple) -> Callable:
    """``fn(img, ref, mask)`` for one metric with its python constants bound."""
    if kind == "ssim_map":
        window, sigma = static
        return lambda a, b, w: _ssim_map_impl(a, b, window, sigma)
    if kind == "ssim":
        window, sigma = static
        return lambda a, b, w: _ssim_impl(a, b, w, window, sigma)
    if kind == "photometric":
        lam, window, sigma = static
        return lambda a, b, w: _photometric_impl(a, b, w, lam, window, sigma)
    raise KeyError(kind)  # pragma: no cover - internal


@functools.lru_cache(maxsize=None)
def _graph(kind: str, has_mask: bool, compiled: bool, grad: bool, static: tuple) -> Callable:
    """One (optionally compiled, optionally value-and-grad) graph per signature.

    MLX compiles one kernel set per input shape/dtype; this cache only keys
    the python-level constants (which metric, mask or not, window, lambda).
    """
    fn = _bind(kind, static)
    if has_mask:
        g = fn
    else:
        g = lambda a, b: fn(a, b, None)  # noqa: E731
    if grad:
        g = mx.value_and_grad(g, argnums=0)
    return mx.compile(g) if compiled else g


def _call(kind, img, ref, w, compiled, grad, static):
    fn = _graph(kind, w is not None, bool(compiled), grad, static)
    return fn(img, ref) if w is None else fn(img, ref, w)


# ----------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------


def l1(img: mx.array, ref: mx.array, mask=None) -> mx.array:
    """Mean absolute error (scalar); with ``mask``, the weighted mean over pixels."""
    _check_pair(img, ref, "l1")
    w = None if mask is None else _as_weights(mask, img, "l1")
    return _l1_impl(img, ref, w)


def mse(img: mx.array, ref: mx.array, mask=None, *, clip: bool = False, backend: str = "reference") -> mx.array:
    """Mean squared error (scalar); with ``mask``, the weighted mean over pixels.

    ``clip``: clip ``img`` to [0, 1] first (the image as displayed).
    ``backend='cpu'`` (or 'auto' off Apple GPUs) sums (H, W, C) images in one
    threaded C++ pass in float64 (``mlx3d/csrc/photometric.cpp``; no
    gradient), which the trainer's per-step PSNR uses; 'reference' is the MLX
    graph (float32 sums), differentiable.
    """
    _check_pair(img, ref, "mse")
    w = None if mask is None else _as_weights(mask, img, "mse")
    from ..render.rasterize import resolve_backend

    if resolve_backend(backend) == "cpu" and img.ndim == 3:
        from mlx3d import native

        from ..render.raster_cpu import get_num_threads

        weights = None if w is None else mx.broadcast_to(w, img.shape[:2]).astype(mx.float32)
        return native.core().mse(img.astype(mx.float32), ref.astype(mx.float32), weights, clip, get_num_threads())
    return _mse_impl(mx.clip(img, 0.0, 1.0) if clip else img, ref, w)


def psnr(img: mx.array, ref: mx.array, mask=None, *, clip: bool = False, backend: str = "reference") -> mx.array:
    """Peak signal-to-noise ratio in dB for data range 1: ``-10 log10(MSE)``.

    The MSE is averaged over channels and pixels (weighted by ``mask`` if
    given).  Identical images would give +inf; the MSE is floored at 1e-10, so
    the result is capped at :data:`PSNR_MAX_DB` (100 dB) and always finite.
    ``clip`` and ``backend`` as in :func:`mse`.
    """
    m = mse(img, ref, mask, clip=clip, backend=backend)
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
    return _call("ssim_map", img, ref, None, compiled, False, (int(window), float(sigma)))


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
    return _call("ssim", img, ref, w, compiled, False, (int(window), float(sigma)))


def _photometric_args(img, ref, lambda_dssim, mask, window, sigma, name):
    _check_pair(img, ref, name)
    lam = float(lambda_dssim)
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"{name}: lambda_dssim must be in [0, 1], got {lambda_dssim}")
    gaussian_window(window, sigma)
    w = None if mask is None else _as_weights(mask, img, name)
    return w, (lam, int(window), float(sigma))


def photometric_loss(
    img: mx.array,
    ref: mx.array,
    lambda_dssim: float = 0.2,
    mask=None,
    *,
    window: int = 11,
    sigma: float = 1.5,
    compiled: bool = True,
    backend: str = "reference",
) -> mx.array:
    """The 3DGS training loss ``(1 - lambda) * L1 + lambda * (1 - SSIM)``.

    ``img`` is the render, ``ref`` the ground-truth photo; ``mask`` weights both
    terms as in :func:`l1` and :func:`ssim`.  Differentiable with ``mx.grad``;
    for the training step prefer :func:`photometric_loss_and_grad` (see the
    module docstring).  ``backend='cpu'`` (or 'auto' off Apple GPUs) computes
    an (H, W, C) loss and its gradient in one threaded C++ pass
    (``mlx3d/csrc/photometric.cpp``; differentiable w.r.t. ``img`` and
    ``ref``, not the mask), which the trainer uses; 'reference' is this
    module's MLX graph, the test oracle.
    """
    w, static = _photometric_args(img, ref, lambda_dssim, mask, window, sigma, "photometric_loss")
    from ..render.rasterize import resolve_backend

    if resolve_backend(backend) == "cpu" and img.ndim == 3 and static[0] > 0.0:  # without SSIM the graph is one pass
        from mlx3d import native

        from ..render.raster_cpu import get_num_threads

        weights = None if w is None else mx.broadcast_to(w, img.shape[:2]).astype(mx.float32)
        return native.core().photometric_loss(img.astype(mx.float32), ref.astype(mx.float32), weights, static[0],
                                              list(_taps(window, sigma)), get_num_threads())
    return _call("photometric", img, ref, w, compiled, False, static)


def photometric_loss_and_grad(
    img: mx.array,
    ref: mx.array,
    lambda_dssim: float = 0.2,
    mask=None,
    *,
    window: int = 11,
    sigma: float = 1.5,
    compiled: bool = True,
) -> Tuple[mx.array, mx.array]:
    """``(loss, d loss / d img)`` of :func:`photometric_loss` as one compiled graph.

    The gradient has the shape of ``img``; push it through the renderer with
    ``mx.vjp(render, primals, [grad])`` (or feed it as the cotangent of the
    rendered image).  ``ref`` and ``mask`` are constants here.
    """
    w, static = _photometric_args(img, ref, lambda_dssim, mask, window, sigma, "photometric_loss_and_grad")
    return _call("photometric", img, ref, w, compiled, True, static)
