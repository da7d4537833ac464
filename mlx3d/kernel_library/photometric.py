"""The 3DGS training loss and the per-step MSE (``mlx3d_photometric_loss``, ``mlx3d_mse``).

The loss is three custom functions added: the render's term ``F(img, sg(ref), sg(w))`` (the loss, its vjp
the gradient the kernel wrote with it), the photo's ``G(sg(img), ref, sg(w))`` (0, its vjp the kernel run
with the images swapped) and, with weights, the mask's ``M(w)`` (0, its vjp an error, as ``_core``'s). MLX
calls a vjp only for what is differentiated, so the photo's kernel pass runs only when ``ref`` is, as with
``_core``'s primitive (the trainer differentiates the render alone).
"""

from __future__ import annotations

import functools

import mlx.core as mx
import numpy as np

from . import _call, _f32, _f32p, _host, _i64, _int, _output, _ptr, _reverse_mode_only, _threads, register

register({
    "mlx3d_photometric_loss": ([_f32p, _f32p, _f32p, _i64, _i64, _i64, _f32, _f32p, _i64, _int, _f32p, _f32p, _f32p], _int),
    "mlx3d_mse": ([_f32p, _f32p, _f32p, _i64, _i64, _i64, _int, _int, _f32p], _int),
})


def _check(op: str, img, ref, weights) -> None:
    """float32 (H, W, C) img and ref of one shape, float32 (H, W) weights or None: ``_core``'s checks."""
    for name, a in (("img", img), ("ref", ref), ("weights", weights)):
        if a is not None and not isinstance(a, mx.array):
            raise TypeError(f"{op}: {name} must be an mlx array, got {type(a).__name__}")
    if img.ndim != 3 or img.shape != ref.shape:
        raise ValueError(f"{op}: img and ref must be (H, W, C) of one shape, got {tuple(img.shape)} and {tuple(ref.shape)}")
    if img.size == 0:
        raise ValueError(f"{op}: the images must not be empty, got {tuple(img.shape)}")
    if img.dtype != mx.float32 or ref.dtype != mx.float32:
        raise TypeError(f"{op}: images must be float32 (the Python wrapper casts them), got {img.dtype} and {ref.dtype}")
    if weights is not None and (weights.dtype != mx.float32 or tuple(weights.shape) != tuple(img.shape[:2])):
        raise ValueError(f"{op}: weights must be float32 (H, W) = {tuple(img.shape[:2])}, got {weights.dtype} {tuple(weights.shape)}")


def _images(op: str, img, ref, weights):
    """The checked images and weights (or None) as C-contiguous numpy arrays."""
    _check(op, img, ref, weights)
    shape = tuple(img.shape)
    return _host(img, "img", shape), _host(ref, "ref", shape), None if weights is None else _host(weights, "weights", shape[:2])


def _loss_and_grad(x: np.ndarray, y: np.ndarray, w, lam: float, taps: np.ndarray, threads: int):
    """(loss (), dloss/dx (H, W, C)) as MLX arrays."""
    (loss, loss_view), (grad, grad_view) = _output(()), _output(x.shape)
    _call("mlx3d_photometric_loss", _ptr(x), _ptr(y), _ptr(w), *x.shape, lam, _ptr(taps), taps.size, threads, None,  # scratch: its own
          _ptr(loss_view), _ptr(grad_view))
    return loss, grad


@functools.lru_cache(maxsize=None)
def _loss_function(lam: float, taps: tuple, threads: int):
    """(render term F, photo term G, mask term M) for these constants; each takes (img, ref[, weights])."""
    taps_array = np.array(taps, np.float32)

    def run(a, b, w):
        return _loss_and_grad(*_images("photometric_loss", a, b, w[0] if w else None), lam, taps_array, threads)

    @mx.custom_function
    def render_term(img, ref, *w):
        return run(img, ref, w)

    @render_term.vjp
    def render_term_vjp(primals, cotangents, outputs):
        return (cotangents[0] * outputs[1], *(mx.zeros_like(a) for a in primals[1:]))

    @mx.custom_function
    def photo_term(img, ref, *w):
        return mx.zeros((), dtype=mx.float32)

    @photo_term.vjp
    def photo_term_vjp(primals, cotangent, output):
        img, ref, *w = primals
        return (mx.zeros_like(img), cotangent * run(ref, img, w)[1], *(mx.zeros_like(a) for a in w))

    @mx.custom_function
    def mask_term(w):
        return mx.zeros((), dtype=mx.float32)

    @mask_term.vjp
    def mask_term_vjp(primals, cotangent, output):
        raise RuntimeError("photometric_loss: the gradient with respect to the mask is not implemented.")

    return tuple(_reverse_mode_only(f, "photometric_loss") for f in (render_term, photo_term, mask_term))


def photometric_loss(img: mx.array, ref: mx.array, weights, lambda_dssim: float, taps, num_threads: int = 0) -> mx.array:
    """(1 - λ) L1 + λ (1 - SSIM) () of float32 (H, W, C) images, optionally weighted per pixel (float32 (H, W)); the SSIM
    window outer(taps, taps) (an odd count). Differentiable with respect to img and ref, not the weights
    (``mlx3d._core.photometric_loss``'s contract; use mlx3d.training.metrics.photometric_loss(backend='cpu'))."""
    taps = tuple(float(t) for t in np.asarray(taps, np.float32).ravel())
    if len(taps) == 0 or len(taps) % 2 == 0:
        raise ValueError("photometric_loss: taps must have an odd, positive length")
    lam = float(np.float32(lambda_dssim))
    if not 0.0 <= lam <= 1.0:
        raise ValueError("photometric_loss: lambda_dssim must be in [0, 1]")
    _check("photometric_loss", img, ref, weights)
    render_term, photo_term, mask_term = _loss_function(lam, taps, _threads(num_threads))
    w = () if weights is None else (mx.stop_gradient(weights),)
    loss = render_term(img, mx.stop_gradient(ref), *w)[0] + photo_term(mx.stop_gradient(img), ref, *w)
    return loss if weights is None else loss + mask_term(weights)


@functools.lru_cache(maxsize=None)
def _mse_function(clip: bool, threads: int):
    @mx.custom_function
    def mse(img, ref, *w):
        x, y, weights = _images("mse", img, ref, w[0] if w else None)
        out, view = _output(())
        _call("mlx3d_mse", _ptr(x), _ptr(y), _ptr(weights), *x.shape, int(clip), threads, _ptr(view))
        return out

    @mse.vjp
    def mse_vjp(primals, cotangent, output):
        raise RuntimeError("mse on the CPU kernel is a metric and has no gradient; use backend='reference' to differentiate it.")

    return _reverse_mode_only(mse, "mse")


def mse(img: mx.array, ref: mx.array, weights, clip: bool = False, num_threads: int = 0) -> mx.array:
    """Mean squared error () of float32 (H, W, C) images (img clipped to [0, 1] first with ``clip``), optionally
    weighted per pixel (float32 (H, W)), summed in float64; no gradient (``mlx3d._core.mse``'s contract; use
    mlx3d.training.metrics.psnr(backend='cpu'))."""
    return _mse_function(bool(clip), _threads(num_threads))(img, ref, *(() if weights is None else (weights,)))
