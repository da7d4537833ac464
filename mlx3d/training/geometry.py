"""Geometry regularisers of surfel training (2DGS): one surface per pixel, normals that agree with depth.

Both act on the geometry channels ``render_gaussians`` composites with the
colour (``render_depth_variance``, ``render_normals``) and only where the
render is opaque enough (alpha >= ``min_alpha``), so background and thin
edges do not pull on them:

- depth variance: the alpha-weighted variance of the Gaussians' camera z along
  each ray, divided by ``scale²`` (the scene extent) so its weight does not
  depend on the scene's units. Zero when every ray meets one surface.
- normal consistency: ``1 - <n_render, n_depth>``, where ``n_render`` is the
  rendered surfel normal and ``n_depth`` the normal of the surface the
  rendered depth map describes (cross product of its central differences,
  unprojected through the camera). Zero when the surfels lie flat on the
  surface they render.

A third term serves any method: the sparse depth of a structure-from-motion
solve. Each point a photo observes (``Dataset.observations``) gives the
camera z of the surface at its pixel; ``sparse_depth_loss`` is the mean L1
distance between the inverse of the rendered (expected) depth there and the
inverse of the point's, times the scene extent (gsplat's depth loss). It holds
down surfaces the photos alone leave ambiguous (a dark, shadowed floor).
"""

from __future__ import annotations

import mlx.core as mx
import numpy as np


class DepthUnprojector:
    """World points of a depth map: ``P(u, v) = origin(u, v) + z · step(u, v)``.

    Exact for every camera model (the lens maps a pixel to a camera-space ray
    whose points are linear in z_cam); the two (H,W,3) float32 maps are
    computed once per camera and cached (keyed by the camera object).
    """

    def __init__(self, max_cameras: int = 512):
        self._cache: dict = {}
        self.max_cameras = max_cameras

    def maps(self, camera) -> tuple[mx.array, mx.array]:
        key = id(camera)
        hit = self._cache.get(key)
        if hit is not None and hit[0] is camera:
            return hit[1], hit[2]
        uv = camera.pixel_centers()
        origin = np.asarray(camera.unproject(uv, np.zeros(uv.shape[:-1])), dtype=np.float64)
        step = np.asarray(camera.unproject(uv, np.ones(uv.shape[:-1])), dtype=np.float64) - origin
        if len(self._cache) >= self.max_cameras:
            self._cache.clear()
        entry = (camera, mx.array(origin.astype(np.float32)), mx.array(step.astype(np.float32)))
        self._cache[key] = entry
        return entry[1], entry[2]

    def points(self, camera, depth: mx.array) -> mx.array:
        """(H,W,3) world points of the (H,W) depth map (camera z)."""
        origin, step = self.maps(camera)
        return origin + depth[..., None] * step


def depth_normals(points: mx.array) -> mx.array:
    """(H-2,W-2,3) unit normals of the (H,W,3) world point map, facing the camera.

    Image x runs right and y down with the camera looking along +z_cam, so
    ``cross(dP/dy, dP/dx)`` points back towards the camera.
    """
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    n = mx.stack(
        [dy[..., 1] * dx[..., 2] - dy[..., 2] * dx[..., 1], dy[..., 2] * dx[..., 0] - dy[..., 0] * dx[..., 2], dy[..., 0] * dx[..., 1] - dy[..., 1] * dx[..., 0]],
        axis=-1,
    )
    return n / mx.sqrt(mx.sum(n * n, axis=-1, keepdims=True) + 1e-20)


def _masked_mean(values: mx.array, mask: mx.array) -> mx.array:
    return mx.sum(values * mask) / mx.maximum(mx.sum(mask), 1.0)


def depth_variance_loss(depth_variance: mx.array, alpha: mx.array, min_alpha: float, scale: float, orthographic: bool = False) -> mx.array:
    """Mean ray variance (H,W) of inverse depth over pixels with alpha >= ``min_alpha``, times ``scale²``
    (dimensionless: the variance of scale/z); with an ``orthographic`` camera the map is that of depth, divided by ``scale²``."""
    mask = mx.stop_gradient((alpha >= min_alpha).astype(mx.float32))
    units = 1.0 / (scale * scale) if orthographic else scale * scale
    return _masked_mean(depth_variance, mask) * units


def normal_consistency_loss(normals: mx.array, depth: mx.array, alpha: mx.array, camera, unprojector: DepthUnprojector, min_alpha: float) -> mx.array:
    """Mean ``1 - <rendered normal, depth normal>`` over interior pixels with alpha >= ``min_alpha``.

    normals (H,W,3) unit rendered normals, depth (H,W) camera z, alpha (H,W).
    """
    n_depth = depth_normals(unprojector.points(camera, depth))
    mask = mx.stop_gradient((alpha[1:-1, 1:-1] >= min_alpha).astype(mx.float32))
    agreement = mx.sum(normals[1:-1, 1:-1] * n_depth, axis=-1)
    return _masked_mean(1.0 - agreement, mask)


def sparse_points(camera, points: np.ndarray, pixels: np.ndarray, index: np.ndarray) -> tuple | None:
    """The depth targets of one view: ``(pixels (K, 2) float32, camera z (K,) float32)`` of the observed
    ``points[index]`` ((M, 3) world) at their observed ``pixels`` ((K, 2), the view's pixels), kept where
    they lie in front of ``camera`` (z beyond its near plane) and inside its image; None when none does."""
    world = np.asarray(points, dtype=np.float64)[np.asarray(index, dtype=np.int64)]
    view = np.asarray(camera.viewmat, dtype=np.float64)
    z = world @ view[2, :3] + view[2, 3]
    xy = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    keep = (z > camera.znear) & (xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] < camera.width) & (xy[:, 1] < camera.height)
    if not keep.any():
        return None
    return xy[keep].astype(np.float32), z[keep].astype(np.float32)


def sparse_depth_loss(depth: mx.array, pixels: np.ndarray, z: np.ndarray, scale: float) -> mx.array:
    """Mean ``|1 / depth[pixel] - 1 / z|`` over the points, times ``scale`` (the scene extent: unit-free).

    depth (H,W) the rendered alpha-normalised camera z, read at each point's pixel (the pixel holding
    ``pixels`` (K, 2), x right and y down from the image's corner); z (K,) the points' camera z. Pixels
    the render leaves empty (depth 0) count as inverse depth 0."""
    h, w = depth.shape
    col = np.clip(np.floor(pixels[:, 0]), 0, w - 1).astype(np.int64)
    row = np.clip(np.floor(pixels[:, 1]), 0, h - 1).astype(np.int64)
    rendered = depth.reshape(-1)[mx.array(row * w + col)]
    inverse = mx.where(rendered > 0, 1.0 / mx.maximum(rendered, 1e-12), 0.0)
    return mx.mean(mx.abs(inverse - mx.array(1.0 / z, dtype=mx.float32))) * scale
