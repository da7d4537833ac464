"""Geometry channels composited with the colour: depth, inverse depth and its square, normals.

Per-Gaussian features are packed into extra rasterizer channels by
``pack`` and turned back into per-pixel maps by ``unpack``. Depth is the
camera z. Two depth models:

- centre (default): each Gaussian contributes the depth of its centre;
- planar (``planar_depth``, for surfels): each Gaussian contributes the depth
  of its plane (through the mean, normal its local z axis) along the pixel's
  ray, to first order around the projected mean:
  ``z(q) = a + g·q`` with q the pixel relative to the image centre, so a
  tilted surface covered by discs renders a smooth, tilted depth map instead
  of steps. ``g`` uses the pinhole (or orthographic) Jacobian at the mean and
  is bounded at grazing angles (|cos| >= 0.1). Its compositing needs 3 depth
  channels instead of 1.

The depth variance is that of inverse depth, 1/z (1/length²), as 2DGS's depth
distortion measures it (in NDC, m = f/(f-n) (1 - n/z)): a ray that mixes a
surface with a far background then varies by about the surface's 1/z, not by
the background's distance. An orthographic camera's NDC depth is affine in z,
so there it is the variance of z (length²). It has its own two channels, E[s]
and E[s²] with s = 1/z - 1/r (orthographic: z - r) about a reference depth r
(the mean visible depth unless given), which keeps float32 cancellation
small; it uses the centres' depths, as the planar second moment would expand
into terms of the size of the whole image's depth range.
"""

from __future__ import annotations

import mlx.core as mx

MIN_COS = 0.1  # planar depth: smallest |cos(ray, normal)| used for the depth slope


def facing_normals(camera, means, quats) -> mx.array:
    """(N,3) world-space unit local z axes of the Gaussians, flipped to face ``camera``.

    The local z axis is a surfel's normal (the thin axis under
    ``GaussianModel.apply_2dgs_constraints``). "Facing" means a negative dot
    product with the viewing direction (from the centre to the mean, or the
    forward axis of an orthographic camera)."""
    q = quats / mx.sqrt(mx.sum(quats * quats, axis=-1, keepdims=True) + 1e-24)  # as quaternion_to_matrix: finite gradient at q = 0
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    axis = mx.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=-1)
    if camera.model == "orthographic":
        view = mx.array(camera.camtoworld[:3, 2], dtype=mx.float32)[None, :]
    else:
        view = means - mx.array(camera.center, dtype=mx.float32)
    sign = mx.where(mx.sum(axis * view, axis=-1, keepdims=True) > 0, -1.0, 1.0)
    return mx.stop_gradient(sign) * axis


def depth_planes(camera, means, normals, depths, means2d):
    """Per-Gaussian ``(a (N,), g (N,2))`` of ``z(q) = a + g·q``, q = pixel - image centre."""
    rot = mx.array(camera.viewmat[:3, :3], dtype=mx.float32)
    n_c = normals @ rot.T
    scale = mx.array([1.0 / camera.fx, 1.0 / camera.fy], dtype=mx.float32)
    if camera.model == "orthographic":
        cos, length, factor = n_c[:, 2], 1.0, 1.0
    else:
        xy = (means @ rot[:2].T + mx.array(camera.viewmat[:2, 3], dtype=mx.float32)) / depths[:, None]
        ray = mx.concatenate([xy, mx.ones_like(xy[:, :1])], axis=1)  # (x/z, y/z, 1)
        cos, length, factor = mx.sum(n_c * ray, axis=-1), mx.linalg.norm(ray, axis=-1), depths
    bound = MIN_COS * length
    cos = mx.where(mx.abs(cos) < bound, mx.where(cos < 0, -bound, bound), cos)
    slope = -n_c[:, :2] * scale * (factor / cos)[:, None]
    centre = mx.array([camera.width / 2.0, camera.height / 2.0], dtype=mx.float32)
    a = depths - mx.sum(slope * (means2d - centre), axis=-1)
    return a, slope


def planes_at_pixels(camera, planes) -> mx.array:
    """(H,W) ``a + g·q`` of composited plane channels (H,W,3) = (a, g_x, g_y) at each pixel centre q (relative to
    the image centre, as ``depth_planes``)."""
    u = mx.arange(camera.width, dtype=mx.float32) + 0.5 - camera.width / 2.0
    v = mx.arange(camera.height, dtype=mx.float32)[:, None] + 0.5 - camera.height / 2.0
    return planes[..., 0] + u * planes[..., 1] + v * planes[..., 2]


def reference_depth(depths, radii) -> mx.array:
    """Mean depth of the visible Gaussians (no gradient): the default variance reference."""
    visible = (radii > 0).astype(mx.float32)
    return mx.stop_gradient(mx.sum(depths * visible) / mx.maximum(mx.sum(visible), 1.0))


def pack(plan, camera, means, quats, proj, reference) -> list:
    """(N,k) feature blocks for the geometry channels of ``plan``, in ``plan.channels`` order."""
    blocks = []
    normals = facing_normals(camera, means, quats) if (plan.normals or plan.planar_depth) else None
    if plan.planar_depth:
        # culled Gaussians (never composited) may sit on the camera plane: keep their division finite
        depths = mx.where(proj.radii > 0, proj.depths, 1.0)
        a, g = depth_planes(camera, means, normals, depths, proj.means2d)
        blocks.append(mx.concatenate([a[:, None], g], axis=1))
    elif plan.depth:
        blocks.append(proj.depths[:, None])
    if plan.depth_variance:
        if camera.model == "orthographic":
            centred = proj.depths - reference
        else:  # culled Gaussians (never composited) may sit on the camera plane: keep 1/z finite
            reference = mx.array(reference, dtype=mx.float32)
            centred = 1.0 / mx.where(proj.radii > 0, proj.depths, 1.0) - mx.where(reference > 0, 1.0 / reference, 0.0)
        blocks.append(mx.stack([centred, centred * centred], axis=1))
    if plan.normals:
        blocks.append(normals)
    return blocks


def unpack(plan, camera, accum, alpha) -> dict:
    """Per-pixel maps from the composited channels after the 3 colour channels (see ``render_gaussians``)."""
    out = {}
    hit = alpha > 0
    inv_alpha = 1.0 / mx.maximum(alpha, 1e-10)
    col = 3
    if plan.depth:
        if plan.planar_depth:
            depth = planes_at_pixels(camera, accum[..., col : col + 3]) * inv_alpha
            col += 3
        else:
            depth = accum[..., col] * inv_alpha
            col += 1
        out["depth"] = mx.where(hit, depth, 0.0)
    if plan.depth_variance:
        first, second = accum[..., col] * inv_alpha, accum[..., col + 1] * inv_alpha
        col += 2
        # E[s²] - E[s]², s = 1/z - 1/r (orthographic: z - r)
        out["depth_variance"] = mx.where(hit, mx.maximum(second - mx.square(first), 0.0), 0.0)
    if plan.normals:
        n = accum[..., col : col + 3]
        length = mx.sqrt(mx.sum(n * n, axis=-1, keepdims=True) + 1e-20)  # finite gradient at n = 0
        out["normals"] = mx.where(hit[..., None], n / length, 0.0)
    return out
