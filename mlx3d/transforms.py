"""Rotations, affine transforms, and applying an affine map to Gaussian splats.

Conventions (used throughout mlx3d):

- Quaternions are ``(w, x, y, z)``, the order of ``mathutils.Quaternion``, and
  rotate column vectors: ``v' = R(q) v``.
- Euler angles ``(rx, ry, rz)`` are rotations about the fixed world X, then Y,
  then Z axis: ``R = Rz @ Ry @ Rx`` (Blender's default ``'XYZ'`` mode).
- An affine map is a 4x4 matrix ``A`` acting on column vectors ``[x, 1]``;
  ``A = T @ R @ S`` composes scale, then rotation, then translation.

``quaternion_to_matrix`` works on numpy and MLX arrays (the renderer uses it on
MLX arrays); everything else here is float64 numpy for exactness.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import TransformError


def _stack_like(like, arrays, axis):
    """``stack`` from the library of ``like`` (numpy, or MLX without importing it here)."""
    if type(like).__module__.startswith("mlx"):
        import mlx.core as mx

        return mx.stack(arrays, axis=axis)
    return np.stack(arrays, axis=axis)


def quaternion_to_matrix(quats):
    """Rotation matrices from quaternions.

    quats: (..., 4) w,x,y,z, any non-zero length (normalised here); numpy or MLX.
    Returns (..., 3, 3) of the same array type. A zero quaternion gives a
    finite (degenerate) matrix rather than NaN.
    """
    norm2 = (quats * quats).sum(axis=-1, keepdims=True)
    q = quats / ((norm2 + 1e-24) ** 0.5)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        _stack_like(quats, [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        _stack_like(quats, [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        _stack_like(quats, [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ]
    return _stack_like(quats, rows, -2)


def matrix_to_quaternion(mats: np.ndarray) -> np.ndarray:
    """Unit quaternions (w,x,y,z), w >= 0, from proper rotation matrices (..., 3, 3).

    Uses the numerically robust branch choice of Shepperd's method.
    """
    m = np.asarray(mats, dtype=np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # Four candidate (unnormalised) quaternions; pick the one with the largest
    # leading component for each matrix.
    trace = m00 + m11 + m22
    cands = np.stack(
        [
            np.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            np.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]], -1),
            np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )  # (..., 4 candidates, 4)
    best = np.argmax(np.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1), axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` of (..., 4) w,x,y,z quaternions (rotation b, then a)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def euler_to_matrix(angles_deg) -> np.ndarray:
    """3x3 rotation ``Rz @ Ry @ Rx`` from Euler angles (rx, ry, rz) in degrees."""
    rx, ry, rz = np.radians(np.asarray(angles_deg, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    rot_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rot_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rot_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rot_z @ rot_y @ rot_x


def compose_affine(scale=1.0, rotation_deg=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 matrix ``T @ R @ S``: scale (scalar or 3 factors), Euler rotation in degrees, translation."""
    m = np.eye(4)
    m[:3, :3] = euler_to_matrix(rotation_deg) @ np.diag(np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)))
    m[:3, 3] = np.asarray(translation, dtype=np.float64)
    return m


@dataclass(frozen=True)
class AffineParts:
    """An affine map split for splats: x' = linear @ x + translation.

    ``rotation`` is the orthogonal factor of the polar decomposition of
    ``linear`` (det -1 for a reflection); view-dependent colour follows it.
    ``uniform_scale`` is set when ``linear`` is a rotation (or reflection)
    times a uniform scale, which allows the exact quaternion fast path.
    """

    linear: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    rotation: np.ndarray  # (3, 3) orthogonal
    uniform_scale: float | None


def split_affine(matrix) -> AffineParts:
    """Validate a 4x4 (or 3x4) affine matrix and split it; raises TransformError.

    An ``AffineParts`` passes through unchanged, so callers can split once."""
    if isinstance(matrix, AffineParts):
        return matrix
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape not in ((4, 4), (3, 4)):
        raise TransformError(f"transform must be a 4x4 or 3x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise TransformError("transform contains NaN or Inf")
    if m.shape == (4, 4) and not np.allclose(m[3], [0, 0, 0, 1], atol=1e-12):
        raise TransformError(f"transform is projective (last row {m[3].tolist()}), expected [0, 0, 0, 1]")
    linear, translation = m[:3, :3], m[:3, 3]
    u, sv, vt = np.linalg.svd(linear)
    if sv[-1] <= 1e-12 * max(sv[0], 1e-300):
        raise TransformError(f"transform is singular (singular values {sv.tolist()})")
    rotation = u @ vt
    s = float(np.cbrt(abs(np.linalg.det(linear))))
    uniform = s if np.allclose(linear.T @ linear, s * s * np.eye(3), rtol=0, atol=1e-9 * s * s) else None
    return AffineParts(linear, translation, rotation, uniform)


def transform_gaussians(matrix, means, quats, log_scales, *, backend: str = "auto"):
    """Apply an affine map to Gaussians: means, orientations and log scales.

    matrix: 4x4 affine or ``AffineParts``; means (N,3), quats (N,4) w,x,y,z,
    log_scales (N,3). Each covariance Σ = R diag(s)² Rᵀ becomes L Σ Lᵀ. For a
    rotation times uniform scale the quaternion is left-multiplied by the
    rotation (its length kept) and log s is added; otherwise each covariance is
    re-decomposed from an SVD of ``L R diag(s)`` (scales then come out sorted
    descending, quaternions normalised). Reflections are handled: a reflected
    Gaussian's covariance equals its rotation by ``-rotation``, a proper
    rotation in 3D. backend: 'native' (threaded C++ in ``mlx3d._core``),
    'numpy' (the reference) or 'auto' (native when the extension loads).
    Returns float32 (means, quats, log_scales); see ``AffineParts`` for the SH rotation.
    """
    if backend not in ("auto", "native", "numpy"):
        raise ValueError(f"backend must be 'auto', 'native' or 'numpy', got {backend!r}")
    parts = split_affine(matrix)
    new_means = (np.asarray(means, dtype=np.float64) @ parts.linear.T + parts.translation).astype(np.float32)
    if parts.uniform_scale is not None:
        proper = parts.rotation if np.linalg.det(parts.rotation) > 0 else -parts.rotation
        q = np.asarray(quats, dtype=np.float64)
        new_quats = quaternion_multiply(np.broadcast_to(matrix_to_quaternion(proper), q.shape), q).astype(np.float32)
        new_scales = (np.asarray(log_scales, dtype=np.float64) + np.log(parts.uniform_scale)).astype(np.float32)
        return new_means, new_quats, new_scales
    if backend != "numpy":
        from . import native

        if backend == "native" or native.available():
            return (new_means, *_covariances_native(native.core(), parts.linear, quats, log_scales))
    return (new_means, *_covariances_numpy(parts.linear, quats, log_scales))


def _covariances_native(core, linear, quats, log_scales):
    q = np.ascontiguousarray(quats, dtype=np.float32)
    s = np.ascontiguousarray(log_scales, dtype=np.float32)
    q_out, s_out = np.empty_like(q), np.empty_like(s)
    core.affine_covariances(np.ascontiguousarray(linear, dtype=np.float64), q, s, q_out, s_out)
    return q_out, s_out


def _covariances_numpy(linear, quats, log_scales):
    rot = quaternion_to_matrix(np.asarray(quats, dtype=np.float64))
    m = linear @ rot * np.exp(np.asarray(log_scales, dtype=np.float64))[:, None, :]
    u, sv, _ = np.linalg.svd(m)
    u[np.linalg.det(u) < 0, :, 2] *= -1.0
    new_scales = np.log(np.maximum(sv, np.finfo(np.float64).tiny))
    return matrix_to_quaternion(u).astype(np.float32), new_scales.astype(np.float32)


def transform_normals(matrix, normals: np.ndarray) -> np.ndarray:
    """Normals (N,3) under an affine map: inverse-transpose, renormalised; zero rows stay zero."""
    parts = split_affine(matrix)
    n = np.asarray(normals, dtype=np.float64) @ np.linalg.inv(parts.linear)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1.0), 0.0).astype(np.float32)


def covariances(quats, log_scales) -> np.ndarray:
    """World covariances (N,3,3) float64 from quaternions (N,4) and log scales (N,3)."""
    rot = quaternion_to_matrix(np.asarray(quats, dtype=np.float64))
    m = rot * np.exp(np.asarray(log_scales, dtype=np.float64))[:, None, :]
    return m @ np.swapaxes(m, -1, -2)
