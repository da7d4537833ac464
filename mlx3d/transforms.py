"""Rotations, affine transforms, and applying an affine map to Gaussian splats.

Conventions (used throughout mlx3d):

- Quaternions are ``(w, x, y, z)`` (scalar first), the order of
  ``mathutils.Quaternion`` and of mlx3D, and rotate column vectors:
  ``v' = R(q) v``, the same rotation as the product ``q (0, v) q*``.
- Euler angles ``(rx, ry, rz)`` in degrees (``euler_to_matrix``) are rotations
  about the fixed world X, then Y, then Z axis: ``R = Rz @ Ry @ Rx`` (Blender's
  default ``'XYZ'`` mode). ``euler_angles_to_matrix`` is mlx3D's: radians and
  ``R = R_a0 @ R_a1 @ R_a2`` for a convention string ``a0 a1 a2``.
- An affine map is a 4x4 matrix ``A`` acting on column vectors ``[x, 1]``;
  ``A = T @ R @ S`` composes scale, then rotation, then translation.

The rotation conversions (``quaternion_to_matrix`` ... ``random_rotations``,
the names of mlx3D's ``mlx3d.transforms``, also importable as
``mlx3d.transforms.rotations``) take numpy or MLX arrays and return the same
kind (MLX results stay differentiable); batch dimensions ``...`` are free.
Lists become float64 numpy. Everything from ``euler_to_matrix`` on is float64
numpy for exactness.
"""

from __future__ import annotations

import sys
import types
from dataclasses import dataclass

import numpy as np

from .errors import TransformError

ROTATION_NAMES = (
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "axis_angle_to_quaternion",
    "quaternion_to_axis_angle",
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "euler_angles_to_matrix",
    "rotation_6d_to_matrix",
    "matrix_to_rotation_6d",
    "quaternion_multiply",
    "quaternion_invert",
    "quaternion_apply",
    "standardize_quaternion",
    "random_quaternions",
    "random_rotations",
)


def _is_mlx(a) -> bool:
    return type(a).__module__.startswith("mlx")


def _lib(a):
    """The array library of ``a``: ``mlx.core`` for MLX arrays, else numpy."""
    if _is_mlx(a):
        import mlx.core as mx

        return mx
    return np


def _array(a):
    """MLX arrays and numpy float arrays as they are; anything else as float64 numpy."""
    if _is_mlx(a) or (isinstance(a, np.ndarray) and np.issubdtype(a.dtype, np.floating)):
        return a
    return np.asarray(a, dtype=np.float64)


def _stack_like(like, arrays, axis):
    """``stack`` from the library of ``like`` (numpy, or MLX without importing it here)."""
    return _lib(like).stack(arrays, axis=axis)


def _norm(a, keepdims=True):
    return _lib(a).linalg.norm(a, axis=-1, keepdims=keepdims)


def quaternion_to_matrix(quats):
    """Rotation matrices from quaternions.

    quats: (..., 4) w,x,y,z, any non-zero length (normalised here); numpy or MLX.
    Returns (..., 3, 3) of the same array type. A zero quaternion gives a
    finite (degenerate) matrix rather than NaN.
    """
    quats = _array(quats)
    norm2 = (quats * quats).sum(axis=-1, keepdims=True)
    q = quats / ((norm2 + 1e-24) ** 0.5)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        _stack_like(quats, [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        _stack_like(quats, [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        _stack_like(quats, [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ]
    return _stack_like(quats, rows, -2)


def matrix_to_quaternion(mats):
    """Unit quaternions (w,x,y,z), w >= 0, from proper rotation matrices (..., 3, 3).

    Uses the numerically robust branch choice of Shepperd's method. numpy
    input gives float64; MLX input gives MLX (differentiable).
    """
    m = mats if _is_mlx(mats) else np.asarray(mats, dtype=np.float64)
    xp = _lib(m)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # Four candidate (unnormalised) quaternions; pick the one with the largest
    # leading component for each matrix.
    trace = m00 + m11 + m22
    cands = xp.stack(
        [
            xp.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            xp.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            xp.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]], -1),
            xp.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )  # (..., 4 candidates, 4)
    best = xp.argmax(xp.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1), axis=-1)
    index = xp.broadcast_to(best[..., None, None], (*best.shape, 1, 4))
    q = xp.take_along_axis(cands, index, axis=-2)[..., 0, :]
    q = q / _norm(q)
    return xp.where(q[..., :1] < 0, -q, q)


def standardize_quaternion(quats):
    """The same rotations with a non-negative real part (q and -q are one rotation)."""
    quats = _array(quats)
    return _lib(quats).where(quats[..., :1] < 0, -quats, quats)


def quaternion_multiply(a, b):
    """Hamilton product ``a ⊗ b`` of (..., 4) w,x,y,z quaternions (rotation b, then a)."""
    a, b = _array(a), _array(b)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return _stack_like(
        a,
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def quaternion_invert(quats):
    """The inverse rotation: the conjugate (w, -x, -y, -z); the inverse of a unit quaternion."""
    quats = _array(quats)
    sign = _lib(quats).array([1.0, -1.0, -1.0, -1.0], dtype=quats.dtype)
    return quats * sign


def quaternion_apply(quats, points):
    """Rotate points (..., 3) by quaternions (..., 4) (normalised here): ``q (0, p) q*``."""
    quats, points = _array(quats), _array(points)
    xp = _lib(quats)
    q = quats / _norm(quats)
    p = xp.concatenate([xp.zeros_like(points[..., :1]), points], axis=-1)
    return quaternion_multiply(quaternion_multiply(q, p), quaternion_invert(q))[..., 1:]


def _half_sinc(angle):
    """sin(angle/2) / angle, with its series near 0."""
    xp = _lib(angle)
    small = xp.abs(angle) < 1e-6
    safe = xp.where(small, xp.ones_like(angle), angle)
    return xp.where(small, 0.5 - angle * angle / 48.0, xp.sin(0.5 * safe) / safe)


def axis_angle_to_quaternion(axis_angle):
    """Quaternions (..., 4) from axis-angle vectors (..., 3): direction = axis, length = angle (radians)."""
    axis_angle = _array(axis_angle)
    angle = _norm(axis_angle)
    return _lib(axis_angle).concatenate([_lib(angle).cos(0.5 * angle), axis_angle * _half_sinc(angle)], axis=-1)


def quaternion_to_axis_angle(quats):
    """Axis-angle vectors (..., 3), angle in [0, π], from quaternions (..., 4) (any length)."""
    q = standardize_quaternion(_array(quats))
    q = q / _norm(q)
    vec = q[..., 1:]
    angle = 2.0 * _lib(q).arctan2(_norm(vec), q[..., :1])
    return vec / _half_sinc(angle)


def axis_angle_to_matrix(axis_angle):
    """Rotation matrices (..., 3, 3) from axis-angle vectors (..., 3)."""
    return quaternion_to_matrix(axis_angle_to_quaternion(axis_angle))


def matrix_to_axis_angle(mats):
    """Axis-angle vectors (..., 3) from rotation matrices (..., 3, 3)."""
    return quaternion_to_axis_angle(matrix_to_quaternion(mats))


def _axis_rotation(axis: str, angle):
    xp = _lib(angle)
    c, s = xp.cos(angle), xp.sin(angle)
    one, zero = xp.ones_like(angle), xp.zeros_like(angle)
    rows = {
        "X": [[one, zero, zero], [zero, c, -s], [zero, s, c]],
        "Y": [[c, zero, s], [zero, one, zero], [-s, zero, c]],
        "Z": [[c, -s, zero], [s, c, zero], [zero, zero, one]],
    }[axis]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def euler_angles_to_matrix(euler_angles, convention: str = "XYZ"):
    """Rotation matrices (..., 3, 3) from Euler angles (..., 3) in radians (mlx3D's convention).

    ``convention`` names the axis of each angle, e.g. ``"XYZ"`` gives
    ``R_X(a0) @ R_Y(a1) @ R_Z(a2)`` (rotations about the moving axes, X first).
    For mlx3d's degree-based Blender convention see ``euler_to_matrix``.
    """
    if not isinstance(convention, str) or len(convention) != 3 or any(c not in "XYZ" for c in convention):
        raise ValueError(f"convention must be 3 letters from 'X', 'Y', 'Z', got {convention!r}")
    euler_angles = _array(euler_angles)
    m = [_axis_rotation(axis, euler_angles[..., i]) for i, axis in enumerate(convention)]
    return m[0] @ m[1] @ m[2]


def rotation_6d_to_matrix(d6):
    """Rotation matrices (..., 3, 3) from the 6D representation (..., 6) (Zhou et al. 2019).

    The two 3-vectors are orthonormalised (Gram-Schmidt) into the first two
    rows; the third row is their cross product."""
    d6 = _array(d6)
    xp = _lib(d6)
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = a1 / xp.maximum(_norm(a1), 1e-12)
    a2 = a2 - (b1 * a2).sum(axis=-1, keepdims=True) * b1
    b2 = a2 / xp.maximum(_norm(a2), 1e-12)
    b3 = xp.linalg.cross(b1, b2) if xp is not np else np.cross(b1, b2)
    return xp.stack([b1, b2, b3], axis=-2)


def matrix_to_rotation_6d(mats):
    """The 6D representation (..., 6): the first two rows of each matrix."""
    mats = _array(mats)
    return mats[..., :2, :].reshape(*mats.shape[:-2], 6)


def random_quaternions(n: int, key=None):
    """``n`` uniformly distributed unit quaternions (n, 4) with w >= 0, as an MLX array
    (``mx.random`` with ``key``, or its global seed)."""
    import mlx.core as mx

    q = mx.random.normal((int(n), 4), key=key)
    return standardize_quaternion(q / mx.linalg.norm(q, axis=-1, keepdims=True))


def random_rotations(n: int, key=None):
    """``n`` uniformly distributed rotation matrices (n, 3, 3), as an MLX array."""
    return quaternion_to_matrix(random_quaternions(n, key))


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


# mlx3D's ``mlx3d.transforms.rotations`` module: the same functions under that name.
rotations = types.ModuleType(__name__ + ".rotations", "Rotation conversions (mlx3D's module name); see mlx3d.transforms.")
rotations.__all__ = list(ROTATION_NAMES)
for _name in ROTATION_NAMES:
    setattr(rotations, _name, globals()[_name])
del _name
sys.modules[rotations.__name__] = rotations
