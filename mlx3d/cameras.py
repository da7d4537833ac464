"""Cameras for the renderer: pose, intrinsics and lens models.

Conventions (shared with the renderer):

- ``viewmat`` is the 4x4 world-to-camera pose with OpenCV camera axes:
  x right, y down, z forward; depth is ``z_cam`` (> 0 in front).
- Pixel coordinates are continuous: x right, y down, origin at the top-left
  corner of the image, so pixel (row i, col j) has its centre at
  ``(j + 0.5, i + 0.5)``. Intrinsics use the same frame (a centred camera has
  ``cx = W / 2``, ``cy = H / 2``).
- ``Camera.from_opengl_c2w`` / ``Camera.to_opengl_c2w`` are the one place that
  converts to and from OpenGL camera axes (x right, y up, looking down -z), as
  used by Blender and NeRF-synthetic ``transforms.json``.

Lens models (``model``):

- ``'pinhole'``: ``u = fx x/z + cx``, ``v = fy y/z + cy``.
- ``'opencv'``: Brown-Conrady, ``dist = (k1, k2, p1, p2, k3)`` in OpenCV's
  order, applied to the normalised point ``(x/z, y/z)`` as in OpenCV's
  ``projectPoints``.
- ``'fisheye'``: Kannala-Brandt as OpenCV's fisheye module,
  ``dist = (k1, k2, k3, k4)``: ``theta = atan(r)``,
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``,
  normalised point scaled by ``theta_d / r``.
- ``'orthographic'``: ``u = fx x + cx``, ``v = fy y + cy`` with ``fx, fy`` in
  pixels per world unit (no division by z).

A distorted lens is one-to-one only up to ``Camera.lens_limit`` off-axis (its
radial polynomial turns back past it); the unscented projection culls
Gaussians reaching beyond it.

Point methods accept numpy arrays (computed in float64) or MLX arrays
(computed in their own floating dtype, differentiable) and return the same
array type. One implementation serves both: the math is plain arithmetic and
only ``stack``/``where``/``sqrt``-like calls go through ``_xp``.

The API of the original mlx3D library's ``mlx3d.cameras`` is accepted as well,
with its meanings: ``Camera(R, t, fx, fy, cx, cy, width, height, znear, zfar,
orthographic, distortion, fisheye)`` (positional or keyword), ``znear``/``zfar``,
``orthographic``/``distortion``/``fisheye``; ``Camera.look_at`` with a y-up
default and a VERTICAL field of view in degrees (default 60) and a 512x512
default size; ``Camera.from_fov``, ``Camera.orthographic_camera``,
``camera_center``, ``world_to_camera_matrix``, ``camera_to_world``,
``unproject_points``, ``generate_rays``; and the module functions ``look_at``,
``look_at_view_transform``, ``fov_to_focal`` and ``focal_to_fov``. Our own
names (``viewmat``, ``near``/``far``, ``model``/``dist``, ``hfov``/``focal``
in ``look_at``) are additions. ``R``, ``t``, ``K`` and ``center`` are float64
numpy arrays; the names that only the original has return float32 MLX arrays
as it does.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass, field

import numpy as np

MODELS = ("pinhole", "opencv", "fisheye", "orthographic")
_DIST_LEN = {"pinhole": 0, "opencv": 5, "fisheye": 4, "orthographic": 0}

# Perspective division uses |z| >= _Z_EPS, so points on the camera plane stay finite.
_Z_EPS = 1e-8
# Brown-Conrady is evaluated with the normalised radius clamped to 1e3 (within
# 0.06 degrees of 90 degrees off-axis), far outside any image, so the polynomial
# cannot overflow for grazing or behind-camera points.
_R2_MAX = 1e6
# Added under square roots of squared radii so the value and the MLX gradient
# stay finite on the optical axis.
_TINY2 = 1e-30
_ORTHO_TOL = 1e-5
_UNDISTORT_ITERS = 20


def _is_mx(a) -> bool:
    return type(a).__module__.startswith("mlx")


def _xp(a):
    """The array library of ``a``: ``mlx.core`` for MLX arrays, else numpy."""
    if _is_mx(a):
        import mlx.core as mx

        return mx
    return np


def _as_float(a, name: str, last: int | None = None):
    """``a`` as a floating array (numpy float64, or MLX in its floating dtype)."""
    if _is_mx(a):
        import mlx.core as mx

        if not mx.issubdtype(a.dtype, mx.floating):
            a = a.astype(mx.float32)
    else:
        try:
            a = np.asarray(a, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name}: expected a numeric array, got {type(a).__name__}") from exc
    if last is not None and (a.ndim < 1 or a.shape[-1] != last):
        raise ValueError(f"{name}: expected shape (..., {last}), got {tuple(a.shape)}")
    return a


def _like(a, ref):
    """``a`` converted to the array library (and, for MLX, the dtype) of ``ref``."""
    if _is_mx(ref):
        import mlx.core as mx

        if _is_mx(a):
            return a.astype(ref.dtype)
        return mx.array(np.asarray(a, dtype=np.float64), dtype=ref.dtype)
    return np.asarray(a, dtype=np.float64)


def _apply(m, x, y, z, translate: bool = True):
    """Rows of the 3x4 (numpy) matrix ``m`` applied to components x, y, z, stacked on the last axis."""
    rows = m.tolist()  # python floats: keep MLX dtypes and never turn MLX into numpy
    out = []
    for r in rows[:3]:
        v = r[0] * x + r[1] * y + r[2] * z
        out.append(v + r[3] if translate else v)
    return _xp(x).stack(out, axis=-1)


def _vec3(v, name: str) -> np.ndarray:
    """A (3,) float64 numpy vector from a sequence, numpy or MLX array."""
    try:
        out = np.array(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 3-vector, got {v!r}") from None
    if out.shape != (3,):
        raise ValueError(f"{name} must be a 3-vector, got shape {out.shape}")
    return out


def _positive_int(value, name: str) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    try:
        n = operator.index(value)
    except TypeError:
        try:
            f = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a positive integer, got {value!r}") from None
        if not f.is_integer():
            raise ValueError(f"{name} must be a positive integer, got {value!r}") from None
        n = int(f)
    if n <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return n


def _finite_float(value, name: str) -> float:
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(f):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return f


def _check_pose(matrix, name: str) -> np.ndarray:
    """A rigid 4x4 float64 copy of ``matrix`` ((4,4) or (3,4)), or ValueError naming ``name``."""
    if _is_mx(matrix):
        matrix = np.array(matrix)
    try:
        m = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 4x4 numeric matrix, got {type(matrix).__name__}") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4) or (3, 4), got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} must be finite, got {m.tolist()}")
    if np.max(np.abs(m[3] - [0.0, 0.0, 0.0, 1.0])) > _ORTHO_TOL:
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    r = m[:3, :3]
    err = float(np.max(np.abs(r @ r.T - np.eye(3))))
    if err > _ORTHO_TOL:
        raise ValueError(
            f"{name}: the 3x3 rotation block is not orthonormal (max |R R^T - I| = {err:.3g}); "
            "remove any scale from the pose"
        )
    if np.linalg.det(r) <= 0:
        raise ValueError(f"{name}: the 3x3 rotation block is a reflection (determinant < 0)")
    m[3] = [0.0, 0.0, 0.0, 1.0]
    return m


_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z; its own inverse

# Constructor argument orders: ours, and the original mlx3D library's (chosen when
# the first positional argument is an array, i.e. its rotation R).
_OUR_ORDER = ("width", "height", "fx", "fy", "cx", "cy", "viewmat", "near", "far", "model", "dist")
_ORIGINAL_ORDER = ("R", "t", "fx", "fy", "cx", "cy", "width", "height", "znear", "zfar", "orthographic",
                   "distortion", "fisheye")
_ARG_NAMES = frozenset(_OUR_ORDER) | frozenset(_ORIGINAL_ORDER)
_REQUIRED = ("width", "height", "fx", "fy", "cx", "cy")
_DEFAULT_NEAR = 0.01
_DEFAULT_FAR = 1e10
_DEFAULT_FOV_DEG = 60.0  # the original's look_at default: vertical, degrees


def _is_array_like(a) -> bool:
    """True for arrays and (nested) sequences, False for scalars: tells R from width."""
    if _is_mx(a):
        return a.ndim >= 1
    if isinstance(a, (str, bytes)):
        return False
    if isinstance(a, (list, tuple)):
        return True
    try:
        return np.ndim(a) >= 1
    except (TypeError, ValueError):
        return False


def _mat3(m, name: str) -> np.ndarray:
    """A (3, 3) finite float64 numpy copy of ``m`` (sequence, numpy or MLX array)."""
    if _is_mx(m):
        m = np.array(m)
    try:
        out = np.array(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 3x3 numeric matrix, got {type(m).__name__}") from None
    if out.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} must be finite, got {out.tolist()}")
    return out


def _translation(t) -> np.ndarray:
    """A (3,) finite float64 vector from a (3,) or (3, 1) sequence, numpy or MLX array."""
    if _is_mx(t):
        t = np.array(t)
    try:
        out = np.array(t, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"t must be a 3-vector, got {t!r}") from None
    if out.size != 3 or out.ndim > 2:
        raise ValueError(f"t must be a 3-vector, got shape {out.shape}")
    out = out.reshape(3)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"t must be finite, got {out.tolist()}")
    return out


def _resolve_pose(args: dict) -> np.ndarray:
    """viewmat from ``viewmat`` and/or the original's ``R`` and ``t``.

    ``R`` and ``t`` replace the rotation and translation of ``viewmat`` (identity
    when absent), so ``dataclasses.replace(cam, R=..., t=...)`` works.
    """
    viewmat = args.get("viewmat")
    if "R" not in args and "t" not in args:
        return np.eye(4) if viewmat is None else viewmat
    m = np.eye(4) if viewmat is None else _check_pose(viewmat, "viewmat")
    if "R" in args:
        r = _mat3(args["R"], "R")
        rm = np.eye(4)
        rm[:3, :3] = r
        _check_pose(rm, "R")  # rigid-rotation checks, reported against R
        m[:3, :3] = r
    if "t" in args:
        m[:3, 3] = _translation(args["t"])
    return m


def _coefficients(d, name: str):
    """A tuple of floats from a sequence / array of coefficients (None and () give None)."""
    if d is None:
        return None
    try:
        out = tuple(float(x) for x in np.asarray(np.array(d) if _is_mx(d) else d, dtype=np.float64).ravel())
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a sequence of numbers, got {d!r}") from None
    return out or None


def _resolve_lens(args: dict):
    """(model, dist) from ours (``model``, ``dist``) and/or the original's lens arguments.

    The original's ``orthographic``, ``distortion`` and ``fisheye`` take precedence
    over ``model``/``dist`` where both are given (as ``dataclasses.replace`` does).
    Brown-Conrady ``distortion`` may have 4 coefficients (k3 = 0) or 5; fisheye 4;
    ``fisheye=True`` without coefficients is the equidistant model.
    """
    model = args.get("model", "pinhole")
    dist = args.get("dist", ())
    if not any(k in args for k in ("orthographic", "distortion", "fisheye")):
        return model, dist
    ortho = args.get("orthographic")
    fisheye = args.get("fisheye")
    if "distortion" in args:
        coeffs = _coefficients(args["distortion"], "distortion")
    else:
        coeffs = _coefficients(dist, "dist") if model in ("opencv", "fisheye") else None
    if ortho is None:
        ortho = model == "orthographic"
    if ortho:
        if fisheye or ("distortion" in args and coeffs is not None and any(coeffs)):
            raise ValueError("lens distortion is not supported for an orthographic camera")
        return "orthographic", ()
    if fisheye is None:
        fisheye = model == "fisheye"
    if fisheye:
        return "fisheye", (0.0, 0.0, 0.0, 0.0) if coeffs is None else coeffs
    if coeffs is None:
        return "pinhole", ()
    if len(coeffs) == 4:
        coeffs = coeffs + (0.0,)
    return "opencv", coeffs


def _focal_from_angle(angle, pixels: int, degrees, name: str) -> float:
    """Focal length in pixels spanning ``pixels`` with field of view ``angle``."""
    a = _finite_float(angle, name)
    rad = math.radians(a) if degrees else a
    if not 0.0 < rad < math.pi:
        unit = "degrees" if degrees else "radians"
        limit = "180" if degrees else "pi"
        raise ValueError(f"{name} must be in (0, {limit}) {unit}, got {angle!r}")
    return pixels / (2.0 * math.tan(rad / 2.0))


def _look_at_pose(eye, at, up):
    """World-to-camera (R, t), float64, for a camera at ``eye`` looking at ``at`` with ``up`` up in the image."""
    eye, at, up = _vec3(eye, "eye"), _vec3(at, "at"), _vec3(up, "up")
    for name, v in (("eye", eye), ("at", at), ("up", up)):
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be finite, got {v.tolist()}")
    forward = at - eye
    dist_ = float(np.linalg.norm(forward))
    if dist_ <= 1e-12 * max(1.0, float(np.linalg.norm(eye))):
        raise ValueError(f"eye and at must differ, got eye={eye.tolist()}, at={at.tolist()}")
    z = forward / dist_
    up_norm = float(np.linalg.norm(up))
    if up_norm == 0.0:
        raise ValueError(f"up must be non-zero, got {up.tolist()}")
    x = np.cross(z, up / up_norm)
    xn = float(np.linalg.norm(x))
    if xn < 1e-9:
        raise ValueError(f"up must not be parallel to the view direction at - eye, got up={up.tolist()}")
    x /= xn
    y = np.cross(z, x)  # image down
    r = np.stack([x, y, z])
    return r, -r @ eye


def fov_to_focal(fov: float, pixels: int) -> float:
    """Focal length in pixels for a field of view ``fov`` in RADIANS across ``pixels``."""
    return pixels / (2.0 * math.tan(fov / 2.0))


def focal_to_fov(focal: float, pixels: int) -> float:
    """Field of view in RADIANS across ``pixels`` for a focal length ``focal`` in pixels."""
    return 2.0 * math.atan(pixels / (2.0 * focal))


def look_at(eye, at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)):
    """World-to-camera ``(R (3, 3), t (3,))`` as float32 MLX arrays, ``x_cam = R x_world + t``.

    OpenCV camera axes; ``up`` points up in the image (it need not be
    perpendicular to the view direction, only not parallel to it).
    ``Camera(R=R, t=t, ...)`` takes the result.
    """
    import mlx.core as mx

    r, t = _look_at_pose(eye, at, up)
    return mx.array(r, dtype=mx.float32), mx.array(t, dtype=mx.float32)


def look_at_view_transform(dist=1.0, elev=0.0, azim=0.0, at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), degrees=True):
    """``look_at`` for a camera on a sphere of radius ``dist`` around ``at``, looking at it.

    ``elev`` is the angle above the xz-plane, ``azim`` the angle about +y measured
    from +z (degrees unless ``degrees=False``): the camera sits at
    ``at + dist (cos(elev) sin(azim), sin(elev), cos(elev) cos(azim))``.
    Returns float32 MLX ``(R, t)``.
    """
    elev, azim = float(elev), float(azim)
    if degrees:
        elev, azim = math.radians(elev), math.radians(azim)
    d = float(dist)
    at = _vec3(at, "at")
    eye = at + d * np.array([math.cos(elev) * math.sin(azim), math.sin(elev), math.cos(elev) * math.cos(azim)])
    return look_at(eye, at, up)


@dataclass(frozen=True, eq=False, init=False)
class Camera:
    """A camera: image size, intrinsics, world-to-camera pose and lens model.

    Two constructor forms, positional or keyword:

    ``Camera(width, height, fx, fy, cx, cy, viewmat=I, near=0.01, far=1e10, model='pinhole', dist=())``

    width, height: image size in pixels.
    fx, fy: focal lengths in pixels (orthographic: pixels per world unit).
    cx, cy: principal point in continuous pixel coordinates (centre = W/2, H/2).
    viewmat: (4, 4) or (3, 4) world-to-camera, OpenCV axes; kept as a read-only
        float64 numpy copy (``viewmat_mx`` is the float32 MLX version).
    near, far: clipping depths (world units along camera z), ``near < far``.
    model: ``'pinhole'``, ``'opencv'``, ``'fisheye'`` or ``'orthographic'``.
    dist: distortion coefficients: ``(k1, k2, p1, p2, k3)`` for ``'opencv'``,
        ``(k1, k2, k3, k4)`` for ``'fisheye'``, ``()`` otherwise.

    ``Camera(R, t, fx, fy, cx, cy, width, height, znear=0.01, zfar=1e10, orthographic=False,
    distortion=None, fisheye=False)``: the original mlx3D library's form (its
    positional order applies when the first positional argument is an array):

    R, t: world-to-camera rotation (3, 3) and translation (3,), ``x_cam = R x_world + t``
        (numpy, MLX or sequences).
    znear, zfar: the same as near, far. (The original's ``zfar`` default is 100,
        which its splatting renderer never reads; here far culls, so the default
        stays 1e10.)
    orthographic: True for ``model='orthographic'``.
    distortion: Brown-Conrady ``(k1, k2, p1, p2[, k3])`` (``model='opencv'``), or with
        ``fisheye=True`` OpenCV fisheye ``(k1, k2, k3, k4)`` (``model='fisheye'``;
        equidistant when None).

    The names of both forms may be mixed; the original's names win where both
    describe the same thing, so ``dataclasses.replace(cam, R=..., znear=...)`` works.

    Frozen: use ``dataclasses.replace`` (which re-validates) for variants.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    viewmat: np.ndarray = field(default_factory=lambda: np.eye(4))
    near: float = 0.01
    far: float = 1e10
    model: str = "pinhole"
    dist: tuple = ()

    def __init__(self, *args, **kwargs):
        order = _ORIGINAL_ORDER if args and _is_array_like(args[0]) else _OUR_ORDER
        if len(args) > len(order):
            raise TypeError(f"Camera() takes at most {len(order)} positional arguments ({len(args)} given)")
        for name, value in zip(order, args):
            if name in kwargs:
                raise TypeError(f"Camera() got multiple values for argument {name!r}")
            kwargs[name] = value
        unknown = sorted(set(kwargs) - _ARG_NAMES)
        if unknown:
            raise TypeError(f"Camera() got an unexpected keyword argument {unknown[0]!r}")
        missing = [name for name in _REQUIRED if name not in kwargs]
        if missing:
            raise TypeError(f"Camera() missing required argument(s): {', '.join(missing)}")
        for name in _REQUIRED:
            object.__setattr__(self, name, kwargs[name])
        model, dist = _resolve_lens(kwargs)
        values = {
            "viewmat": _resolve_pose(kwargs),
            "near": kwargs.get("znear", kwargs.get("near", _DEFAULT_NEAR)),
            "far": kwargs.get("zfar", kwargs.get("far", _DEFAULT_FAR)),
            "model": model,
            "dist": dist,
        }
        for name, value in values.items():
            object.__setattr__(self, name, value)
        self.__post_init__()

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        put("width", _positive_int(self.width, "width"))
        put("height", _positive_int(self.height, "height"))
        for name in ("fx", "fy"):
            v = _finite_float(getattr(self, name), name)
            if v <= 0:
                raise ValueError(f"{name} must be positive, got {v!r}")
            put(name, v)
        for name in ("cx", "cy"):
            put(name, _finite_float(getattr(self, name), name))
        vm = _check_pose(self.viewmat, "viewmat")
        vm.setflags(write=False)
        put("viewmat", vm)

        if not isinstance(self.model, str) or self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        near = _finite_float(self.near, "near")
        try:
            far = float(self.far)
        except (TypeError, ValueError):
            raise ValueError(f"far must be a real number, got {self.far!r}") from None
        if math.isnan(far):
            raise ValueError(f"far must not be NaN, got {self.far!r}")
        if self.model != "orthographic" and near <= 0:
            raise ValueError(f"near must be positive for model {self.model!r}, got {near!r}")
        if not near < far:
            raise ValueError(f"near must be less than far, got near={near!r}, far={far!r}")
        put("near", near)
        put("far", far)

        dist = () if self.dist is None else self.dist
        try:
            dist = tuple(float(d) for d in np.asarray(dist, dtype=np.float64).ravel())
        except (TypeError, ValueError):
            raise ValueError(f"dist must be a sequence of numbers, got {self.dist!r}") from None
        want = _DIST_LEN[self.model]
        if len(dist) != want:
            raise ValueError(
                f"dist must have {want} coefficients for model {self.model!r}, got {len(dist)}: {self.dist!r}"
            )
        if not all(math.isfinite(d) for d in dist):
            raise ValueError(f"dist must be finite, got {self.dist!r}")
        put("dist", dist)

    # -- equality (viewmat is an array, so the dataclass default cannot be used)

    def _key(self):
        return (self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.viewmat.tobytes(),
                self.near, self.far, self.model, self.dist)

    def __eq__(self, other):
        if not isinstance(other, Camera):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self):
        return hash(self._key())

    # -- derived quantities

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def R(self) -> np.ndarray:
        """(3, 3) float64 world-to-camera rotation."""
        return self.viewmat[:3, :3].copy()

    @property
    def t(self) -> np.ndarray:
        """(3,) float64 world-to-camera translation: ``x_cam = R x_world + t``."""
        return self.viewmat[:3, 3].copy()

    @property
    def znear(self) -> float:
        """``near`` (the original mlx3D library's name)."""
        return self.near

    @property
    def zfar(self) -> float:
        """``far`` (the original mlx3D library's name)."""
        return self.far

    @property
    def orthographic(self) -> bool:
        """True for ``model='orthographic'``."""
        return self.model == "orthographic"

    @property
    def fisheye(self) -> bool:
        """True for ``model='fisheye'``."""
        return self.model == "fisheye"

    @property
    def distortion(self) -> tuple | None:
        """The lens coefficients (``dist``) of ``'opencv'`` / ``'fisheye'``, None otherwise."""
        return self.dist if self.model in ("opencv", "fisheye") else None

    @property
    def camera_center(self):
        """(3,) camera centre in world coordinates, a float32 MLX array (``center`` is numpy float64)."""
        import mlx.core as mx

        return mx.array(self.center, dtype=mx.float32)

    @property
    def world_to_camera_matrix(self):
        """(4, 4) world-to-camera matrix, a float32 MLX array (the same as ``viewmat_mx``)."""
        return self.viewmat_mx

    @property
    def viewmat_mx(self):
        """``viewmat`` as a (4, 4) float32 MLX array."""
        import mlx.core as mx

        return mx.array(self.viewmat, dtype=mx.float32)

    @property
    def camtoworld(self) -> np.ndarray:
        """(4, 4) float64 camera-to-world pose (inverse of ``viewmat``), OpenCV axes.

        Inverted in closed form (rows of R^-1 from cross products): a LAPACK
        inverse would wake numpy's BLAS threads, which then spin on the cores
        the renderer's threads need, every step.
        """
        r, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        adj = np.stack([np.cross(r[1], r[2]), np.cross(r[2], r[0]), np.cross(r[0], r[1])], axis=1)  # R adj = det(R) I
        inv = adj / float(r[0] @ adj[:, 0])
        out = np.eye(4)
        out[:3, :3] = inv
        out[:3, 3] = -(inv @ t)
        return out

    @property
    def center(self) -> np.ndarray:
        """(3,) float64 camera centre in world coordinates."""
        return self.camtoworld[:3, 3].copy()

    @property
    def needs_ut(self) -> bool:
        """True when EWA's pinhole Jacobian is not this camera's projection.

        That is ``'opencv'`` with any non-zero coefficient, ``'fisheye'`` and
        ``'orthographic'``; False for ``'pinhole'`` (and all-zero ``'opencv'``).
        """
        if self.model == "pinhole":
            return False
        if self.model == "opencv":
            return any(d != 0.0 for d in self.dist)
        return True

    def _fov(self, axis: int) -> float:
        if self.model == "orthographic":
            raise ValueError(f"field of view is undefined for model {self.model!r}")
        if axis == 0:
            uv = np.array([[0.0, self.cy], [float(self.width), self.cy]])
        else:
            uv = np.array([[self.cx, 0.0], [self.cx, float(self.height)]])
        d = self._pixel_rays_camera(uv)
        ang = np.arctan2(d[axis], d[2])
        return float(ang[1] - ang[0])

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in radians, edge to edge through the principal point.

        Pinhole: ``atan(cx/fx) + atan((W - cx)/fx)`` (``2 atan(W / 2fx)`` when
        centred); distorted models use the undistorted edge rays. ValueError for
        ``'orthographic'``.
        """
        return self._fov(0)

    @property
    def fov_y(self) -> float:
        """Vertical field of view in radians (as ``fov_x``, along y)."""
        return self._fov(1)

    # -- constructors

    @classmethod
    def look_at(cls, eye, at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=None, width=512, height=512, degrees=True,
                *, hfov=None, focal=None, **kw) -> "Camera":
        """A camera at ``eye`` looking at ``at``, with ``up`` pointing up in the image.

        The original mlx3D library's signature and meanings, plus ``hfov`` and ``focal``.

        eye, at, up: (3,) world coordinates / direction. ``up`` defaults to +y (a
            y-up world); it need not be perpendicular to the view direction, only
            not parallel to it. The camera's y axis (image down) is the part of
            ``-up`` perpendicular to the view direction; its x axis (image right)
            is ``forward x up``.
        fov: VERTICAL field of view, in degrees (radians with ``degrees=False``),
            across ``height``: ``fx = fy = (H/2) / tan(fov/2)``. Default 60 degrees.
        width, height: image size in pixels (default 512 x 512).
        hfov: instead of ``fov``, the HORIZONTAL field of view across ``width``
            (same unit as ``fov``): ``fx = fy = (W/2) / tan(hfov/2)``.
        focal: instead of ``fov``, the focal length in pixels.
            At most one of ``fov``, ``hfov``, ``focal``. For an orthographic camera
            the resulting number is used as pixels per world unit, as in the
            original (``Camera.orthographic_camera`` takes a view size instead).
        kw: other ``Camera`` arguments of either form (``near``/``znear``,
            ``far``/``zfar``, ``model``/``orthographic``, ``dist``/``distortion``/``fisheye``),
            not the pose.
        The principal point is the image centre ``(W/2, H/2)``.
        """
        r, t = _look_at_pose(eye, at, up)
        for name in ("viewmat", "R", "t"):
            if name in kw:
                raise TypeError(f"look_at sets the pose from eye, at and up; {name!r} cannot be given")
        width = _positive_int(width, "width")
        height = _positive_int(height, "height")
        given = [name for name, v in (("fov", fov), ("hfov", hfov), ("focal", focal)) if v is not None]
        if len(given) > 1:
            raise ValueError(f"give at most one of fov (vertical), hfov (horizontal) and focal (pixels), "
                             f"got {', '.join(given)}")
        if focal is not None:
            f = _finite_float(focal, "focal")
            if f <= 0:
                raise ValueError(f"focal must be positive, got {focal!r}")
        elif hfov is not None:
            f = _focal_from_angle(hfov, width, degrees, "hfov")
        else:
            if fov is None:
                fov = _DEFAULT_FOV_DEG if degrees else math.radians(_DEFAULT_FOV_DEG)
            f = _focal_from_angle(fov, height, degrees, "fov")
        viewmat = np.eye(4)
        viewmat[:3, :3] = r
        viewmat[:3, 3] = t
        return cls(width=width, height=height, fx=f, fy=f, cx=width / 2.0, cy=height / 2.0, viewmat=viewmat, **kw)

    @classmethod
    def from_fov(cls, fov, width, height, R=None, t=None, degrees=True, **kw) -> "Camera":
        """A centred camera from a VERTICAL field of view (degrees unless ``degrees=False``).

        ``fx = fy = (H/2) / tan(fov/2)``, ``cx, cy = W/2, H/2``. R, t: world-to-camera
        pose (identity when omitted). kw: other ``Camera`` arguments of either form.
        """
        width = _positive_int(width, "width")
        height = _positive_int(height, "height")
        f = _focal_from_angle(fov, height, degrees, "fov")
        if R is not None:
            kw["R"] = R
        if t is not None:
            kw["t"] = t
        return cls(width=width, height=height, fx=f, fy=f, cx=width / 2.0, cy=height / 2.0, **kw)

    @classmethod
    def orthographic_camera(cls, scale, width, height, R=None, t=None, **kw) -> "Camera":
        """A centred orthographic camera seeing ``[-scale, scale]`` world units vertically.

        ``fx = fy = (H/2) / scale`` pixels per world unit (the width follows from
        the aspect ratio). R, t: world-to-camera pose (identity when omitted).
        kw: other ``Camera`` arguments of either form.
        """
        width = _positive_int(width, "width")
        height = _positive_int(height, "height")
        s = _finite_float(scale, "scale")
        if s <= 0:
            raise ValueError(f"scale must be positive, got {scale!r}")
        if R is not None:
            kw["R"] = R
        if t is not None:
            kw["t"] = t
        return cls(width=width, height=height, fx=(height / 2.0) / s, fy=(height / 2.0) / s, cx=width / 2.0,
                   cy=height / 2.0, orthographic=True, **kw)

    @classmethod
    def from_opengl_c2w(cls, c2w, width, height, fx, fy=None, cx=None, cy=None, **kw) -> "Camera":
        """A camera from a camera-to-world pose with OpenGL axes (x right, y up, looking down -z).

        c2w: (4, 4) or (3, 4) rigid matrix (Blender ``matrix_world`` without
            scale, NeRF-synthetic ``transform_matrix``).
        fx, fy: pixels (``fy`` defaults to ``fx``); cx, cy default to the image centre.
        kw: other ``Camera`` fields.
        """
        c2w_gl = _check_pose(c2w, "c2w")
        c2w_cv = c2w_gl @ _GL_TO_CV
        r = c2w_cv[:3, :3]
        viewmat = np.eye(4)
        viewmat[:3, :3] = r.T
        viewmat[:3, 3] = -r.T @ c2w_cv[:3, 3]
        width = _positive_int(width, "width")
        height = _positive_int(height, "height")
        fy = fx if fy is None else fy
        cx = width / 2.0 if cx is None else cx
        cy = height / 2.0 if cy is None else cy
        return cls(width, height, fx, fy, cx, cy, viewmat, **kw)

    def to_opengl_c2w(self) -> np.ndarray:
        """(4, 4) float64 camera-to-world pose with OpenGL axes (inverse of ``from_opengl_c2w``)."""
        return self.camtoworld @ _GL_TO_CV

    def scaled(self, factor) -> "Camera":
        """This camera for the image resized by ``factor`` (e.g. 0.5 for half size).

        The new size is ``round(W * factor)``, ``round(H * factor)`` (halves up);
        fx, cx scale by the actual ratio ``W'/W`` and fy, cy by ``H'/H``, so the
        continuous frame maps exactly (corner (W, H) goes to (W', H')).
        Distortion coefficients act on normalised coordinates and are kept.
        """
        f = _finite_float(factor, "factor")
        if f <= 0:
            raise ValueError(f"factor must be positive, got {factor!r}")
        w = int(math.floor(self.width * f + 0.5))
        h = int(math.floor(self.height * f + 0.5))
        if w < 1 or h < 1:
            raise ValueError(f"factor {factor!r} makes a {self.width}x{self.height} image empty ({w}x{h})")
        sx, sy = w / self.width, h / self.height
        return Camera(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.viewmat,
                      near=self.near, far=self.far, model=self.model, dist=self.dist)

    # -- points

    def world_to_camera(self, points):
        """Camera-space points (..., 3) from world points (..., 3); same array type."""
        p = _as_float(points, "points", 3)
        return _apply(self.viewmat[:3], p[..., 0], p[..., 1], p[..., 2])

    def camera_to_world(self, points_cam):
        """World points (..., 3) from camera-space points (..., 3); same array type."""
        p = _as_float(points_cam, "points_cam", 3)
        return _apply(self.camtoworld[:3], p[..., 0], p[..., 1], p[..., 2])

    @property
    def lens_limit(self) -> float:
        """How far off-axis the lens model stays one-to-one: the largest squared normalised radius
        ``(x/z)² + (y/z)²`` (``'opencv'``) or squared angle θ² in radians² (``'fisheye'``) up to which the
        distorted radius still grows with the true one; ``inf`` for pinhole and orthographic cameras
        and for coefficients that never fold.

        Past it the polynomial turns back (a negative ``k1`` makes ``r (1 + k1 r²)`` fall from
        ``r = 1 / sqrt(3 |k1|)``): a point far outside the picture lands inside it, mirrored. Tangential
        terms are not counted (they are small where lenses are calibrated)."""
        if self.model == "opencv":
            k1, k2, _, _, k3 = self.dist
            derivative = (7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0)  # d[r (1 + k1 r² + k2 r⁴ + k3 r⁶)]/dr in u = r²
        elif self.model == "fisheye":
            k1, k2, k3, k4 = self.dist
            derivative = (9.0 * k4, 7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0)  # d theta_d / d theta in u = θ²
        else:
            return math.inf
        roots = np.roots(np.trim_zeros(np.array(derivative, np.float64), "f"))
        folds = [r.real for r in roots if abs(r.imag) < 1e-12 and r.real > 0]
        return float(min(folds)) if folds else math.inf

    def camera_to_pixels(self, points_cam, eps=_Z_EPS):
        """Pixels of camera-space points: ``(uv (..., 2) pixels, depth (...,) = z_cam)``.

        Applies the lens model only (no pose); used on camera-space sigma points.
        Points behind or on the camera plane give finite (meaningless) pixels;
        cull them with depth. Perspective division uses ``|z| >= eps`` (sign kept).
        """
        p = _as_float(points_cam, "points_cam", 3)
        xp = _xp(p)
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        if self.model == "orthographic":
            xn, yn = x, y
        elif self.model == "fisheye":
            # atan2(rho, z) = atan(r) in front of the camera and extends past 90 degrees.
            k1, k2, k3, k4 = self.dist
            rho = xp.sqrt(x * x + y * y + _TINY2)
            theta = xp.arctan2(rho, z)
            t2 = theta * theta
            theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
            s = theta_d / rho
            xn, yn = x * s, y * s
        else:
            zs = xp.where(z >= 0, xp.maximum(z, eps), xp.minimum(z, -eps))
            xn, yn = x / zs, y / zs
            if self.model == "opencv":
                r2 = xn * xn + yn * yn
                shrink = xp.where(r2 > _R2_MAX, xp.sqrt(_R2_MAX / xp.maximum(r2, _R2_MAX)), 1.0)
                xn, yn = _brown_conrady(xn * shrink, yn * shrink, self.dist)
        uv = xp.stack([self.fx * xn + self.cx, self.fy * yn + self.cy], axis=-1)
        return uv, z

    def project_points(self, points, eps=_Z_EPS):
        """Project world points (..., 3): ``(uv (..., 2) pixels, depth (...,) = z_cam)``.

        Same array type as ``points``; differentiable for MLX arrays. Depth is not
        culled: points behind the camera have negative depth; mask on it.
        """
        return self.camera_to_pixels(self.world_to_camera(points), eps=eps)

    def _pixel_rays_camera(self, uv):
        """Camera-space ray (dx, dy, dz), not unit, through pixels ``uv`` of a projective model.

        The point at depth z on the ray is ``(dx, dy, dz) * z / dz``; ``dz = 1.0``
        except for the fisheye model (where the ray is unit).
        """
        u, v = uv[..., 0], uv[..., 1]
        xd = (u - self.cx) / self.fx
        yd = (v - self.cy) / self.fy
        if self.model == "pinhole":
            return xd, yd, 1.0
        if self.model == "opencv":
            xn, yn = _undistort_brown_conrady(xd, yd, self.dist)
            return xn, yn, 1.0
        if self.model == "fisheye":
            xp = _xp(uv)
            theta_d = xp.sqrt(xd * xd + yd * yd + _TINY2)
            theta = _undistort_theta(theta_d, self.dist)
            s = xp.sin(theta) / theta_d
            return xd * s, yd * s, xp.cos(theta)
        raise ValueError(f"no perspective rays for model {self.model!r}")

    def _pixels_depth(self, uv, depth):
        uv = _as_float(uv, "uv", 2)
        if _is_mx(depth) and not _is_mx(uv):
            uv = _like(uv, depth)
        depth = _like(_as_float(depth, "depth"), uv)
        if tuple(depth.shape) != tuple(uv.shape[:-1]):
            depth = _xp(uv).broadcast_to(depth, tuple(uv.shape[:-1]))
        return uv, depth

    def unproject(self, uv, depth):
        """World points (..., 3) at ``depth`` (z_cam, (...,) or scalar) behind pixels ``uv`` (..., 2).

        Inverse of ``project_points``. Distorted models invert the lens with 20
        Newton iterations (exact to rounding wherever the distortion is monotonic
        along the ray); pinhole and orthographic are closed form. Returns the
        array type of ``uv`` (MLX if either input is MLX).
        """
        uv, depth = self._pixels_depth(uv, depth)
        if self.model == "orthographic":
            xc = (uv[..., 0] - self.cx) / self.fx
            yc = (uv[..., 1] - self.cy) / self.fy
            zc = depth
        else:
            dx, dy, dz = self._pixel_rays_camera(uv)
            s = depth / dz
            xc, yc, zc = dx * s, dy * s, depth
        return _apply(self.camtoworld[:3], xc, yc, zc)

    def unproject_points(self, xy, depth):
        """``unproject`` under the original mlx3D library's name."""
        return self.unproject(xy, depth)

    def pixel_centers(self) -> np.ndarray:
        """(H, W, 2) float64 continuous coordinates of every pixel centre, ``(j + 0.5, i + 0.5)``."""
        u = np.arange(self.width, dtype=np.float64) + 0.5
        v = np.arange(self.height, dtype=np.float64) + 0.5
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv], axis=-1)

    def rays(self, uv=None):
        """World rays through pixels: ``(origins (..., 3), directions (..., 3) unit)``.

        uv: (..., 2) pixels; None means every pixel centre, giving (H, W, 3).
        Perspective models: origins are the camera centre. Orthographic: origins
        on the camera plane (z_cam = 0), directions the camera's forward axis.
        """
        uv = self.pixel_centers() if uv is None else _as_float(uv, "uv", 2)
        c2w = self.camtoworld[:3]
        if self.model == "orthographic":
            xc = (uv[..., 0] - self.cx) / self.fx
            yc = (uv[..., 1] - self.cy) / self.fy
            origins = _apply(c2w, xc, yc, xc * 0.0)
            zero = xc * 0.0
            dirs = _apply(c2w, zero, zero, zero + 1.0, translate=False)
            return origins, dirs
        dx, dy, dz = self._pixel_rays_camera(uv)
        dz = dx * 0.0 + dz
        inv = 1.0 / _xp(dx).sqrt(dx * dx + dy * dy + dz * dz)
        dirs = _apply(c2w, dx * inv, dy * inv, dz * inv, translate=False)
        zero = dx * 0.0
        origins = _apply(c2w, zero, zero, zero)
        return origins, dirs

    def generate_rays(self):
        """One ray per pixel centre: ``(origins, directions)``, (H, W, 3) float32 MLX arrays.

        ``rays()`` as MLX arrays (the original mlx3D library's name and type);
        directions are unit.
        """
        import mlx.core as mx

        origins, dirs = self.rays()
        return mx.array(origins, dtype=mx.float32), mx.array(dirs, dtype=mx.float32)


def _brown_conrady(x, y, dist):
    """OpenCV's radial (k1, k2, k3) + tangential (p1, p2) distortion of normalised (x, y)."""
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = x * y
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    return xd, yd


def _undistort_brown_conrady(xd, yd, dist):
    """Normalised (x, y) whose Brown-Conrady distortion is (xd, yd): Newton from (xd, yd)."""
    k1, k2, p1, p2, k3 = dist
    if not any(dist):
        return xd, yd
    xp = _xp(xd)
    x, y = xd, yd
    for _ in range(_UNDISTORT_ITERS):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + r2 * 3.0 * k3)  # d radial / d r2
        xy = x * y
        fx_ = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x) - xd
        fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy - yd
        cross = 2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x  # d fx / dx
        d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x  # d fy / dy
        det = a * d - cross * cross
        det = xp.where(xp.abs(det) < 1e-12, 1e-12, det)
        step_x = (d * fx_ - cross * fy_) / det
        step_y = (a * fy_ - cross * fx_) / det
        x, y = x - step_x, y - step_y
        if xp is np and np.all(np.abs(step_x) + np.abs(step_y) <= 1e-15 * (1.0 + np.abs(x) + np.abs(y))):
            break
    return x, y


def _undistort_theta(theta_d, dist):
    """theta in [0, pi] with ``theta (1 + k1 theta^2 + ... + k4 theta^8) = theta_d``: Newton."""
    k1, k2, k3, k4 = dist
    if not any(dist):
        return theta_d
    xp = _xp(theta_d)
    theta = theta_d
    for _ in range(_UNDISTORT_ITERS):
        t2 = theta * theta
        f = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        df = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        df = xp.where(xp.abs(df) < 1e-12, 1e-12, df)
        step = f / df
        theta = xp.minimum(xp.maximum(theta - step, 0.0), math.pi)
        if xp is np and np.all(np.abs(step) <= 1e-15 * (1.0 + theta)):
            break
    return theta
