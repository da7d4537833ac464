"""Projection of 3D Gaussians to 2D image-space Gaussians (MLX, differentiable).

Two methods, one result type (``Projection``, used inside the renderer):

- EWA (``project_ewa``): the camera-space covariance is pushed through
  the Jacobian of the pinhole projection at the Gaussian's centre, with x/z and
  y/z clamped to 1.3 times the half field of view (so that off-screen Gaussians
  do not explode). Exact for pinhole cameras only.
- Unscented transform (``project_ut``): 6 sigma points at
  ``mean ± sqrt(3)·L_k`` (L = R·diag(s), so Σ = L Lᵀ) go through
  ``camera.camera_to_pixels`` — any camera model: distorted, fisheye,
  orthographic — and their spread gives the 2D covariance (exact for linear
  maps, second-order accurate otherwise).

Both add ``blur`` (pixels², default 0.3 as in 3DGS) to the 2D covariance; with
``antialias`` the opacity is scaled by sqrt(det Σ / det(Σ + blur·I)) as in
Mip-Splatting. A Gaussian is culled (radius 0) when its centre is nearer than
``camera.near`` or farther than ``camera.far``, its blurred 2D covariance is
not positive definite (determinant ≤ 0, negative diagonal, or not finite), or its 3σ box misses the image.
Culled Gaussians produce finite values everywhere, so their gradients are
exactly zero rather than NaN. ``means2d`` is the projected centre of every
Gaussian in front of the camera, on screen or not (0 behind it or where it is
not finite).

The public ``project_gaussians`` / ``project_gaussians_ut`` return the same
values as a dict, as the original mlx3D did: ``means2d``, ``conics``,
``depths``, ``radii`` (float32) and ``compensation``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import mlx.core as mx
import numpy as np

from ..transforms import quaternion_to_matrix

# 3-sigma extent and the minimum eigenvalue floor used for radii (3DGS: 0.1)
SIGMA_EXTENT = 3.0
_EIGEN_FLOOR = 0.1
# largest radius stored (pixels): far beyond any image, and exact in float32 and int32
_MAX_RADIUS = float(2**30)


class Projection(NamedTuple):
    """Image-space Gaussians. Shapes for N Gaussians:

    means2d (N,2) pixels; conics (N,3) = (a, b, c) of Σ2D⁻¹ = [[a,b],[b,c]];
    radii (N,) int32 pixels (0 = culled, at most 2**30); depths (N,) camera z;
    compensation (N,) opacity factor (1 without antialias).
    """

    means2d: mx.array
    conics: mx.array
    radii: mx.array
    depths: mx.array
    compensation: mx.array


def quat_scale_to_cov3d(quats: mx.array, scales: mx.array) -> mx.array:
    """World covariances (N,3,3) = R diag(s)² Rᵀ from quats (N,4) w,x,y,z and std-devs (N,3)."""
    m = quaternion_to_matrix(quats) * scales[:, None, :]
    return m @ mx.swapaxes(m, -1, -2)


def _camera_arrays(camera):
    view = mx.array(camera.viewmat, dtype=mx.float32)
    return view[:3, :3], view[:3, 3]


@mx.custom_function
def _inverse_2x2(a, b, c, det):
    """(N,3) conics (A, B, C) = (c, -b, a) / det of the symmetric [[a, b], [b, c]] with determinant ``det``.

    The gradient is written with the conic itself, dK = -K dΣ K, instead of differentiating the
    quotients: for a very wide Gaussian (Σ ≳ 1e12 px²) the quotient rule overflows float32 (det²,
    cotangent · c) and gives NaN or wrong values, while -K G K stays representable. ``det`` stands
    for a·c - b² (possibly computed more accurately) and gets no gradient of its own.
    """
    return mx.stack([c / det, -b / det, a / det], axis=-1)


@_inverse_2x2.vjp
def _inverse_2x2_vjp(primals, cotangent, output):
    A, B, C = output[:, 0], output[:, 1], output[:, 2]
    ga, gb, gc = cotangent[:, 0], cotangent[:, 1], cotangent[:, 2]
    # K = [[A, B], [B, C]], dK = -K dΣ K with dΣ = E11 (a), E12 + E21 (b), E22 (c)
    da = -((ga * A) * A + (gb * A) * B + (gc * B) * B)
    db = -(2.0 * (ga * A) * B + gb * (A * C + B * B) + 2.0 * (gc * B) * C)
    dc = -((ga * B) * B + (gb * B) * C + (gc * C) * C)
    return da, db, dc, mx.zeros_like(primals[3])


def _finish(camera, means2d, cov2d, depths, valid, blur, antialias, det_orig=None) -> Projection:
    """Blur, invert and size the 2D covariances ((N,) arrays a, b, c of [[a, b], [b, c]]); cull; build the result.

    det_orig: the determinant of the unblurred covariance when the caller has it in a more
    accurate form than a·c - b² (then the blurred one is det_orig + blur·(a + c) + blur²).
    """
    a, b, c = cov2d
    in_front = valid
    # A covariance that overflowed float32 (UT sigma points sent ~1e19 px apart by a distorted lens
    # far outside its image) is culled, and replaced first: its inf would otherwise meet the zero
    # cotangent of the masks below in the backward pass (0 · inf = NaN).
    fits = mx.stop_gradient(mx.isfinite(a) & mx.isfinite(b) & mx.isfinite(c))
    a, b, c = mx.where(fits, a, 1.0), mx.where(fits, b, 0.0), mx.where(fits, c, 1.0)
    valid = valid & fits
    if det_orig is None:
        det_orig = a * c - b * b
        a, c = a + blur, c + blur
        det = a * c - b * b
    else:
        det = det_orig + blur * (a + c) + blur * blur
        a, c = a + blur, c + blur
    valid = valid & (det > 0) & (a > 0) & mx.isfinite(det)  # positive definite
    safe_det = mx.where(valid, det, 1.0)
    if antialias:
        # det_orig masked like det, both divided by the (constant) det first so that the quotient's
        # gradient never squares a huge det (float32 overflow, then NaN), and sqrt only where the
        # ratio is positive: an inf or NaN det_orig of a culled Gaussian, or the infinite slope of
        # sqrt at 0 for a flat (rank-1 2D) one, would otherwise reach the parameters as 0 · inf = NaN
        unit = mx.stop_gradient(safe_det)
        ratio = (mx.where(valid, det_orig, 0.0) / unit) / (safe_det / unit)
        live = valid & (ratio > 0)
        compensation = mx.where(live, mx.sqrt(mx.where(live, ratio, 1.0)), 0.0)
    else:
        compensation = mx.where(valid, 1.0, 0.0)
    # culled rows invert the identity: the VJP multiplies by the conic, which must stay finite
    conics = _inverse_2x2(mx.where(valid, a, 1.0), mx.where(valid, b, 0.0), mx.where(valid, c, 1.0), safe_det)
    conics = mx.where(valid[:, None], conics, 0.0)
    # radius from the larger eigenvalue (no gradient: it only selects tiles)
    mid = mx.stop_gradient(0.5 * (a + c))
    lam = mid + mx.sqrt(mx.maximum(mid * mid - mx.stop_gradient(safe_det), _EIGEN_FLOOR))
    radius = mx.ceil(SIGMA_EXTENT * mx.sqrt(mx.maximum(lam, 0.0)))
    m2 = mx.stop_gradient(means2d)
    on_screen = (m2[:, 0] + radius > 0) & (m2[:, 0] - radius < camera.width) & (m2[:, 1] + radius > 0) & (m2[:, 1] - radius < camera.height)
    valid = valid & on_screen & mx.isfinite(radius)
    # a finite radius can still exceed int32 (UT through a strongly distorted lens): clamp before the cast
    radii = mx.where(valid, mx.minimum(radius, _MAX_RADIUS), 0.0).astype(mx.int32)
    # the centre stays meaningful off screen; behind the camera (or overflowing) it is replaced by 0
    centred = in_front & mx.stop_gradient(mx.all(mx.isfinite(means2d), axis=-1))
    means2d = mx.where(centred[:, None], means2d, 0.0)
    return Projection(means2d, conics, radii, depths, compensation)


def project_ewa(camera, means, quats, scales, blur: float = 0.3, antialias: bool = False, backend: str = "auto") -> Projection:
    """EWA projection. means (N,3) world, quats (N,4) w,x,y,z (any length), scales (N,3) std-devs.

    backend: 'cpu' runs the threaded C++ primitive (``mlx3d/csrc/projection_math.h``, with its
    own backward pass); 'metal' and 'reference' the MLX expression below, the test oracle;
    'auto' as ``resolve_backend``. Differentiable w.r.t. means, quats and scales either way.
    """
    from .rasterize import resolve_backend

    if resolve_backend(backend) == "cpu":
        from mlx3d import native

        from .raster_cpu import get_num_threads

        f32 = [mx.array(a, dtype=mx.float32) if not isinstance(a, mx.array) else a.astype(mx.float32) for a in (means, quats, scales)]
        viewmat = [float(v) for v in np.asarray(camera.viewmat, np.float64).reshape(-1)]
        m2, conics, radii, depths, comp = native.core().project_ewa(
            *f32, viewmat, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, camera.near, camera.far,
            float(blur), bool(antialias), get_num_threads())
        return Projection(m2, conics, radii, depths, comp)
    return _project_ewa_reference(camera, means, quats, scales, blur, antialias)


def _project_ewa_reference(camera, means, quats, scales, blur: float, antialias: bool) -> Projection:
    """``project_ewa`` in MLX operations (autodiff gives its gradients)."""
    rot, trans = _camera_arrays(camera)
    p = means @ rot.T + trans
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    valid = (z >= camera.near) & (z <= camera.far) & mx.isfinite(z)
    zs = mx.where(valid, z, 1.0)
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    tan_x, tan_y = 0.5 * camera.width / fx, 0.5 * camera.height / fy
    # clamp x/z and y/z to the frustum widened by 30% of the half field of view
    tx = zs * mx.clip(x / zs, -(cx / fx + 0.3 * tan_x), (camera.width - cx) / fx + 0.3 * tan_x)
    ty = zs * mx.clip(y / zs, -(cy / fy + 0.3 * tan_y), (camera.height - cy) / fy + 0.3 * tan_y)
    # Σ2D = J Σcam Jᵀ with Σcam = L Lᵀ, L = rot · R(q) · diag(s) (the Gaussian's axes in camera
    # space) and the Jacobian J = [[fx/z, 0, -fx tx/z²], [0, fy/z, -fy ty/z²]]: Σ2D = T Tᵀ with
    # T = J L. Written out per entry on (N,) arrays, as batched 3x3 matmuls cost one small GEMM
    # call per Gaussian; T Tᵀ is also positive semi-definite by construction.
    r = quaternion_to_matrix(quats)  # (N,3,3)
    rs = [[r[:, i, k] * scales[:, k] for k in range(3)] for i in range(3)]
    axes = [[rot[i, 0] * rs[0][k] + rot[i, 1] * rs[1][k] + rot[i, 2] * rs[2][k] for k in range(3)] for i in range(3)]
    j00, j02 = fx / zs, -fx * tx / (zs * zs)
    j11, j12 = fy / zs, -fy * ty / (zs * zs)
    t0 = [j00 * axes[0][k] + j02 * axes[2][k] for k in range(3)]
    t1 = [j11 * axes[1][k] + j12 * axes[2][k] for k in range(3)]
    cov2d = (
        t0[0] * t0[0] + t0[1] * t0[1] + t0[2] * t0[2],
        t0[0] * t1[0] + t0[1] * t1[1] + t0[2] * t1[2],
        t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2],
    )
    # det(T Tᵀ) as the sum of the squared 2x2 minors of T (Cauchy-Binet): never negative, and
    # exactly 0 for a Gaussian flat in the view direction (T of rank 1), which is then culled.
    minors = [t0[i] * t1[j] - t0[j] * t1[i] for i, j in ((0, 1), (0, 2), (1, 2))]
    det_orig = minors[0] * minors[0] + minors[1] * minors[1] + minors[2] * minors[2]
    means2d = mx.stack([fx * x / zs + cx, fy * y / zs + cy], axis=-1)
    return _finish(camera, means2d, cov2d, z, valid, blur, antialias, det_orig)


def project_ut(camera, means, quats, scales, blur: float = 0.3, antialias: bool = False) -> Projection:
    """Unscented-transform projection through ``camera.camera_to_pixels`` (any camera model).

    Same arguments and result as ``project_ewa``. A Gaussian is culled
    when any sigma point is nearer than ``camera.near`` or farther off-axis than
    the lens model stays one-to-one (``Camera.lens_limit``): past that a distorted
    lens folds far-away points back into the picture, and one Gaussian straddling
    the fold spreads over all of it.
    """
    rot, trans = _camera_arrays(camera)
    p = means @ rot.T + trans
    axes = rot @ (quaternion_to_matrix(quats) * scales[:, None, :])  # (N,3,3): columns L_k in camera space
    offsets = (3.0**0.5) * mx.swapaxes(axes, -1, -2)  # (N,3,3): row k = sqrt(3) L_k
    sigma = mx.concatenate([p[:, None, :] + offsets, p[:, None, :] - offsets], axis=1)  # (N,6,3)
    z = p[:, 2]
    valid = (z <= camera.far) & mx.isfinite(z) & mx.all(sigma[..., 2] >= camera.near, axis=1)
    limit = camera.lens_limit
    if math.isfinite(limit):  # every sigma point where the lens is one-to-one, else it folds back into the picture
        sz = mx.maximum(sigma[..., 2], camera.near)
        r2 = (sigma[..., 0] * sigma[..., 0] + sigma[..., 1] * sigma[..., 1]) / (sz * sz)
        off_axis = mx.arctan(mx.sqrt(r2)) ** 2 if camera.model == "fisheye" else r2
        valid = valid & mx.stop_gradient(mx.all(off_axis < limit, axis=1))
    safe_p = mx.where(valid[:, None], p, mx.array([0.0, 0.0, 1.0]))
    safe_sigma = mx.where(valid[:, None, None], sigma, mx.array([0.0, 0.0, 1.0]))
    centre = camera.camera_to_pixels(safe_p)[0]  # (N,2)
    spread = camera.camera_to_pixels(safe_sigma)[0] - centre[:, None, :]  # (N,6,2)
    cov2d = (mx.swapaxes(spread, -1, -2) @ spread) / 6.0
    return _finish(camera, centre, (cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]), z, valid, blur, antialias)



def projection_dict(proj: Projection) -> dict:
    """The public (original mlx3D) form of a ``Projection``: a dict of (N,...) arrays.

    ``means2d`` (N,2) pixel centres, ``conics`` (N,3) upper triangle (a, b, c)
    of the inverse 2D covariance, ``depths`` (N,) camera z, ``radii`` (N,)
    float32 pixel radii (0 = culled), ``compensation`` (N,) antialiasing
    opacity factor (1 without antialias, 0 for culled Gaussians).
    """
    return {
        "means2d": proj.means2d,
        "conics": proj.conics,
        "depths": proj.depths,
        "radii": proj.radii.astype(mx.float32),
        "compensation": proj.compensation,
    }


def project_gaussians(camera, means, quats, scales, blur: float = 0.3, antialias: bool = False) -> dict:
    """Project 3D Gaussians to the image with EWA splatting (pinhole cameras).

    camera: a ``Camera``; means (N,3) world centres; quats (N,4) rotations
    (w, x, y, z), any length; scales (N,3) standard deviations; blur: pixels²
    added to the 2D covariance's diagonal (0.3 as in 3DGS); antialias: also
    compute the Mip-Splatting opacity compensation sqrt(det Σ / det(Σ + blur I)).

    Returns a dict (see ``projection_dict``): ``means2d``, ``conics``,
    ``depths``, ``radii``, ``compensation``. Differentiable except ``radii``.
    The distortion of an ``'opencv'``/``'fisheye'`` camera and orthographic
    cameras are not represented by EWA: use ``project_gaussians_ut``.
    """
    return projection_dict(project_ewa(camera, means, quats, scales, blur, antialias))


def project_gaussians_ut(camera, means, quats, scales, blur: float = 0.3, antialias: bool = False) -> dict:
    """Project 3D Gaussians with a 3D unscented transform through the camera's own model.

    Six sigma points per Gaussian go through ``camera.camera_to_pixels``, so
    Brown-Conrady and fisheye distortion and orthographic cameras are exact
    for the centres and second-order accurate for the covariances. Same
    arguments and dict as ``project_gaussians``.
    """
    return projection_dict(project_ut(camera, means, quats, scales, blur, antialias))
