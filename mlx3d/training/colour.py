"""Colour correction for evaluation: a per-view affine colour map fitted by least squares.

Photos of one scene can differ in exposure and white balance, and a model
trained on them settles at some compromise (or, with the bilateral grid, at
whatever colour the grid leaves it). Its held-out render can then be right
in every detail and still sit at another exposure than the held-out photo,
which plain PSNR counts as error. Reference evaluations therefore also
report a *colour-corrected* PSNR (mip-NeRF 360's ``color_correct``, gsplat's
``cc_psnr``): the render is first mapped to the photo's colours by the best
global colour transform, then compared. A low PSNR with a high CC-PSNR says
"right content, other exposure"; both low says the content is wrong.

The map fitted here is affine, ``out = A @ rgb + b`` for every pixel, held as
one ``(C, C + 1)`` matrix ``[A | b]`` (3x4 for RGB): per-channel gain and
offset plus channel mixing, the model of an exposure/white-balance change
(and of one cell of the bilateral grid). mip-NeRF 360 fits a quadratic
expansion instead and drops clipped pixels; an affine map is enough for
global exposure and colour-balance differences, has a unique closed-form
optimum, and cannot bend tone curves into real structure.

Images are arrays of shape ``(..., C)`` (usually ``(H, W, 3)``), numpy or MLX,
values nominally in ``[0, 1]``; every leading axis is a pixel axis, so one map
is fitted for everything passed in. ``mask`` is an optional per-pixel weight
of shape ``img.shape[:-1]`` (or broadcastable to it; booleans read as 0/1),
as in :mod:`mlx3d.training.metrics`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["identity_colour_map", "fit_colour_map", "apply_colour_map", "colour_correct"]


def identity_colour_map(channels: int = 3) -> np.ndarray:
    """The ``(C, C + 1)`` map that changes nothing: ``[I | 0]`` (float64)."""
    return np.hstack([np.eye(channels), np.zeros((channels, 1))])


def _pixels(a, name: str) -> np.ndarray:
    x = np.asarray(a, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] < 1:
        raise ValueError(f"{name}: images must be (..., C) arrays, got shape {x.shape}")
    return x


def _weights(mask, pix_shape: tuple) -> np.ndarray | None:
    if mask is None:
        return None
    w = np.asarray(mask, dtype=np.float64)
    try:
        w = np.broadcast_to(w, pix_shape)
    except ValueError:
        raise ValueError(f"colour correction: mask of shape {w.shape} does not broadcast to the image pixels {pix_shape}") from None
    if not (np.isfinite(w).all() and (w >= 0).all()):
        raise ValueError("colour correction: mask weights must be finite and >= 0")
    return w.reshape(-1)


def _sse(pred: np.ndarray, y: np.ndarray, w: np.ndarray | None) -> float:
    e = np.sum((pred - y) ** 2, axis=-1)
    return float(e.sum() if w is None else w @ e)


def fit_colour_map(img, ref, mask=None) -> np.ndarray:
    """The affine colour map from ``img`` (render) to ``ref`` (ground truth), as a ``(C, C + 1)`` float64 matrix.

    ``[A | b]`` minimises the (mask-weighted) sum over pixels of
    ``|A @ img[p] + b - ref[p]|^2``: the linear regression of each ground-truth
    channel on the render's channels and a constant. It is computed in
    float64 from the weighted means and covariances,
    ``A = Cov(ref, img) @ pinv(Cov(img, img))`` and ``b = mean(ref) - A @ mean(img)``;
    the pseudo-inverse picks the smallest map where the render's colours do
    not span every direction (a grey or constant render): a constant render
    maps to the mean colour of ``ref``, a grey one to the best grey-to-colour
    ramp. No mask weight at all (all zeros) gives the identity map. Should
    rounding ever leave the fit worse than the identity (or not finite), the
    identity is returned, so a corrected render never fits worse than the
    original one.
    """
    x, y = _pixels(img, "fit_colour_map"), _pixels(ref, "fit_colour_map")
    if x.shape != y.shape:
        raise ValueError(f"fit_colour_map: image shapes differ: {x.shape} vs {y.shape}")
    c = x.shape[-1]
    w = _weights(mask, x.shape[:-1])
    x, y = x.reshape(-1, c), y.reshape(-1, c)
    identity = identity_colour_map(c)
    if x.shape[0] == 0 or not (np.isfinite(x).all() and np.isfinite(y).all()):
        return identity
    total = float(x.shape[0]) if w is None else float(w.sum())
    if not total > 0.0:
        return identity
    mean_x = (x.sum(0) if w is None else w @ x) / total
    mean_y = (y.sum(0) if w is None else w @ y) / total
    xc, yc = x - mean_x, y - mean_y
    wxc = xc if w is None else xc * w[:, None]
    cov_xx = wxc.T @ xc / total  # (C, C), symmetric positive semi-definite
    cov_xy = wxc.T @ yc / total  # (C, C): Cov(img channel i, ref channel j)
    # Minimum-norm solution of cov_xx @ A.T = cov_xy; singular values below
    # 1e-10 of the largest count as zero (float64 keeps 16 digits, the
    # covariances of float32 images about 7).
    a_t = np.linalg.lstsq(cov_xx, cov_xy, rcond=1e-10)[0] if cov_xx.any() else np.zeros((c, c))
    a = a_t.T
    fitted = np.hstack([a, (mean_y - a @ mean_x)[:, None]])
    if not np.isfinite(fitted).all():
        return identity
    if _sse(x @ fitted[:, :c].T + fitted[:, c], y, w) > _sse(x, y, w):
        return identity
    return fitted


def apply_colour_map(img, matrix, clip: bool = True):
    """``A @ img + b`` per pixel for ``matrix = [A | b]`` of shape ``(C, C + 1)``; clipped to ``[0, 1]`` unless ``clip=False``.

    Returns the type ``img`` came as: an MLX array in ``img``'s dtype, or a
    numpy array (float32 for float32 input, else float64).
    """
    x = _pixels(img, "apply_colour_map")
    m = np.asarray(matrix, dtype=np.float64)
    c = x.shape[-1]
    if m.shape != (c, c + 1):
        raise ValueError(f"apply_colour_map: a map for {c} channels is ({c}, {c + 1}), got {m.shape}")
    out = x @ m[:, :c].T + m[:, c]
    if clip:
        out = np.clip(out, 0.0, 1.0)
    return _like(out, img)


def _like(out: np.ndarray, img):
    try:
        import mlx.core as mx
    except ImportError:  # pragma: no cover - MLX is a dependency
        mx = None
    if mx is not None and isinstance(img, mx.array):
        return mx.array(out.astype(np.float32)).astype(img.dtype)
    dtype = np.float32 if getattr(img, "dtype", None) == np.float32 else np.float64
    return out.astype(dtype)


def colour_correct(img, ref, mask=None, clip: bool = True):
    """``img`` (the render) mapped to the colours of ``ref`` (the ground truth) by the best affine colour map.

    img, ref: ``(..., C)`` arrays (numpy or MLX), values in ``[0, 1]``; ``mask``:
    optional per-pixel weights of shape ``img.shape[:-1]`` for the fit. The map
    is :func:`fit_colour_map`'s least-squares fit (float64); the result,
    ``clip(A @ img + b, 0, 1)``, has ``img``'s shape and type (see
    :func:`apply_colour_map`). Clipping to the range of ``ref`` only moves
    pixels closer to it, so the corrected render is never farther from ``ref``
    (in masked squared error) than ``img`` itself: colour-corrected PSNR >=
    PSNR. Correcting a corrected render again changes nothing (up to rounding)
    where the first correction clipped no pixel.
    """
    corrected = apply_colour_map(img, fit_colour_map(img, ref, mask), clip=clip)
    # Guard the claim above also for inputs outside [0, 1], where clipping could move pixels away from ref.
    x, y, z = _pixels(img, "colour_correct"), _pixels(ref, "colour_correct"), _pixels(corrected, "colour_correct")
    w = _weights(mask, x.shape[:-1])
    c = x.shape[-1]
    if _sse(z.reshape(-1, c), y.reshape(-1, c), w) > _sse(x.reshape(-1, c), y.reshape(-1, c), w):
        return apply_colour_map(img, identity_colour_map(c), clip=False)
    return corrected
