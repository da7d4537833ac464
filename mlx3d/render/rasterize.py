"""Compositing binned 2D Gaussians: the backend dispatch and the public rasterize functions.

``composite`` runs one of the rasterizers ('cpu': the C++ MLX primitive of
``mlx3d._core``, 'metal': Apple GPUs, 'mlx': tiles composited with MLX
operations, which runs anywhere MLX does, 'reference': pure MLX, the test
oracle; 'auto' as ``resolve_backend``) on ``Bins``; ``composite_features`` adds the per-channel
background, alpha normalisation and channel chunking. The public
``rasterize_features``, ``rasterize_depth`` and ``rasterize`` take the tuple of
``bin_gaussians`` (``sorted_ids, tile_ranges, tiles_x, tiles_y``) and return
dicts, as the original mlx3D did; they are differentiable with respect to
means2d, conics, features (or depths) and opacities.
"""

from __future__ import annotations

import mlx.core as mx

from .binning import TILE_SIZE, Bins, bins_from_ranges

BACKENDS = ("auto", "cpu", "metal", "mlx", "reference")
CHUNK_SIZE = 16  # feature channels composited per pass in ``composite_features``


def resolve_backend(backend: str) -> str:
    """'auto' -> 'metal' on Apple GPUs, else 'cpu' where the compiled module ``mlx3d._core`` loads, else 'mlx'.

    The backend names every stage of a render and a training step: 'cpu' runs
    the C++ kernels of ``mlx3d._core`` (and raises ``ExtensionBuildError``
    where it is missing); every other backend runs MLX operations, with the
    Metal kernels for the rasterizer on 'metal'.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        from .. import native
        from .raster_metal import metal_available

        if metal_available():
            return "metal"
        return "cpu" if native.available() else "mlx"
    return backend


def composite(means2d, conics, features, opacities, bins: Bins, width: int, height: int, background=None, backend: str = "auto"):
    """Composite (N,C) features of projected, binned Gaussians front to back.

    Returns ``(image (H,W,C), alpha (H,W), last (H,W) int32)``; ``last`` is 1 +
    the position of the last contributing entry in the pixel's tile range (0
    if none). background: None (black) or (C,) added where the image is not opaque.
    """
    backend = resolve_backend(backend)
    args = (means2d, conics, features, opacities, bins.tile_offsets, bins.flatten_ids, width, height, bins.tile_size)
    if backend == "reference":
        from .raster_reference import rasterize_reference

        accum, alpha, last = rasterize_reference(*args)
    elif backend == "cpu":  # the background composited in the kernel's threads, the integer inputs from our binning
        from .raster_cpu import rasterize_cpu

        return rasterize_cpu(*args, background=background, check_indices=False)
    elif backend == "mlx":
        from .raster_mlx import rasterize_mlx

        accum, alpha, last = rasterize_mlx(*args, check_indices=False)
    else:
        from .raster_metal import rasterize_metal

        accum, alpha, last = rasterize_metal(*args, check_indices=False)
    if background is not None:
        accum = accum + (1.0 - alpha)[..., None] * mx.array(background, dtype=mx.float32)
    return accum, alpha, last


def _feature_background(background, channels: int):
    if background is None:
        return None
    bg = mx.array(background, dtype=mx.float32)
    if bg.ndim == 0:
        bg = mx.broadcast_to(bg, (channels,))
    if bg.shape != (channels,):
        raise ValueError(f"background must have shape ({channels},) or be a scalar, got {tuple(bg.shape)}")
    return bg


def composite_features(
    means2d, conics, features, opacities, bins: Bins, width: int, height: int, background=None, normalize: bool = False,
    backend: str = "auto", chunk_size: int = CHUNK_SIZE,
) -> dict:
    """Composite arbitrary (N,C) features, ``chunk_size`` channels per pass.

    background: None, a scalar or (C,), composited where the image is not
    opaque; ignored with ``normalize``, which divides by alpha instead (the
    alpha-weighted mean of the features, 0 where nothing is hit).
    Returns ``{"features" (H,W,C), "alpha" (H,W), "final_T" (H,W) = 1 - alpha,
    "n_contrib" (H,W) int32}`` (``n_contrib``: see ``composite``'s ``last``).
    """
    features = features if isinstance(features, mx.array) else mx.array(features)
    if features.ndim != 2:
        raise ValueError(f"features must have shape (N, C), got {tuple(features.shape)}")
    if features.shape[0] != means2d.shape[0]:
        raise ValueError(f"features and means2d must have the same first dimension, got {features.shape[0]} and {means2d.shape[0]}")
    channels = int(features.shape[1])
    if channels < 1:
        raise ValueError("features must contain at least one channel")
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    bg = None if normalize else _feature_background(background, channels)
    parts, alpha, last = [], None, None
    for start in range(0, channels, chunk_size):
        part_bg = None if bg is None else bg[start : start + chunk_size]
        accum, alpha, part_last = composite(means2d, conics, features[:, start : start + chunk_size], opacities, bins, width, height, part_bg, backend)
        last = part_last if last is None else last
        parts.append(accum)
    image = mx.concatenate(parts, axis=-1) if len(parts) > 1 else parts[0]
    if normalize:
        image = mx.where(alpha[..., None] > 0, image / mx.maximum(alpha[..., None], 1e-10), 0.0)
    return {"features": image, "alpha": alpha, "final_T": 1.0 - alpha, "n_contrib": last}


def rasterize_features(
    means2d, conics, features, opacities, sorted_ids, tile_ranges, width: int, height: int, tiles_x: int, tiles_y: int,
    background=None, normalize: bool = False, *, backend: str = "auto", tile_size: int = TILE_SIZE, chunk_size: int = CHUNK_SIZE,
) -> dict:
    """Alpha-composite per-Gaussian feature channels of binned 2D Gaussians.

    means2d (N,2), conics (N,3), features (N,C), opacities (N,) in [0, 1];
    ``sorted_ids, tile_ranges, tiles_x, tiles_y`` from ``bin_gaussians``;
    background: None, a scalar or (C,) (ignored with ``normalize``);
    normalize: return the expected feature sum(alpha_i T_i f_i) / alpha (0
    where alpha is 0) instead of the composite with background.

    Returns ``{"features" (H,W,C), "alpha" (H,W), "final_T" (H,W),
    "n_contrib" (H,W) int32}``. Differentiable w.r.t. means2d, conics,
    features and opacities. Keyword-only additions: ``backend`` ('auto',
    'cpu', 'metal', 'reference'), ``tile_size`` (the binning's),
    ``chunk_size`` (channels per pass).
    """
    bins = bins_from_ranges(sorted_ids, tile_ranges, width, height, tiles_x, tiles_y, tile_size)
    return composite_features(means2d, conics, features, opacities, bins, width, height, background, normalize, backend, chunk_size)


def rasterize_depth(
    means2d, conics, opacities, depths, sorted_ids, tile_ranges, width: int, height: int, tiles_x: int, tiles_y: int,
    *, backend: str = "auto", tile_size: int = TILE_SIZE,
) -> dict:
    """Expected depth of binned 2D Gaussians: sum(alpha_i T_i z_i) / alpha, 0 where alpha is 0.

    Arguments as ``rasterize_features`` with ``depths`` (N,) in place of
    features. Returns ``{"depth" (H,W), "alpha" (H,W), "final_T" (H,W)}``
    (and ``"n_contrib"``). Unlike the original's forward-only kernel this one
    is differentiable.
    """
    depths = depths if isinstance(depths, mx.array) else mx.array(depths)
    out = rasterize_features(means2d, conics, depths.reshape(-1, 1), opacities, sorted_ids, tile_ranges, width, height, tiles_x, tiles_y,
                             normalize=True, backend=backend, tile_size=tile_size)
    return {"depth": out["features"][..., 0], "alpha": out["alpha"], "final_T": out["final_T"], "n_contrib": out["n_contrib"]}


def rasterize(
    means2d, conics, colors, opacities, sorted_ids, tile_ranges, width: int, height: int, tiles_x: int, tiles_y: int,
    background=None, *, backend: str = "auto", tile_size: int = TILE_SIZE,
) -> dict:
    """Alpha-composite binned 2D Gaussians into an image: ``rasterize_features`` for colours.

    Returns ``{"image" (H,W,C), "alpha", "final_T", "n_contrib"}``.
    """
    out = rasterize_features(means2d, conics, colors, opacities, sorted_ids, tile_ranges, width, height, tiles_x, tiles_y,
                             background=background, backend=backend, tile_size=tile_size)
    return {"image": out["features"], "alpha": out["alpha"], "final_T": out["final_T"], "n_contrib": out["n_contrib"]}
