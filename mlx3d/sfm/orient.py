"""Where solved cameras land: gravity up, the scene in the middle, a unit of size.

Structure from motion fixes a scene only up to a similarity: its rotation,
origin and scale are whatever the first image pair gave. :func:`upright`
chooses them from the cameras alone, so that a solved capture lands upright
in Blender (``+Z`` up) at a size that suits its default view:

- **up**: the mean of the cameras' up vectors (``-y`` of OpenCV's camera
  axes, in world space), the direction a person holding a camera keeps up. When
  the camera centres lie near a plane (a ring around an object, a walk on
  level ground) and its normal is within 30 degrees of that mean, the plane's
  normal is used instead: a ring's normal is gravity even when every photo
  looks down at the object.
- **forward**: the cameras' mean viewing direction, laid flat, becomes ``+Y``
  (Blender's front view looks along ``+Y``); when they look every way (an
  orbit) the first camera's direction is used.
- **origin**: what the cameras look at (the point nearest every optical axis,
  :func:`mlx3d.training.initial.look_at_centre`), which falls back towards the
  cameras' centroid when they all look the same way.
- **scale**: the cameras' median distance from that origin becomes
  ``target_distance`` (default 4 units).

The result is a 4x4 similarity ``M`` (``x_new = M @ [x, 1]``, ``M = s [R | t]``
with ``R`` a rotation), to apply to points and camera-to-world poses alike.
"""

from __future__ import annotations

import math

import numpy as np

#: The cameras' median distance from what they look at, after :func:`upright`.
TARGET_DISTANCE = 4.0

_PLANE_FLATNESS = 0.1  # smallest PCA variance below this fraction of the middle one: a plane
_PLANE_MAX_TILT = math.radians(30.0)


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-12 else v * 0.0


def up_direction(centres: np.ndarray, ups: np.ndarray) -> np.ndarray:
    """(3,) unit world up from camera centres (N, 3) and camera up vectors (N, 3) (see the module doc)."""
    up = _unit(np.asarray(ups, np.float64).mean(axis=0))
    if not up.any():
        raise ValueError("the cameras' up vectors cancel out: cannot tell which way is up")
    centres = np.asarray(centres, np.float64)
    if len(centres) >= 4:
        values, vectors = np.linalg.eigh(np.cov((centres - centres.mean(axis=0)).T))
        normal = vectors[:, 0]
        if values[0] < _PLANE_FLATNESS * values[1]:
            cos = float(normal @ up)
            if abs(cos) >= math.cos(_PLANE_MAX_TILT):
                return normal * math.copysign(1.0, cos)
    return up


def _rotation_to_z(up: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking ``up`` to +Z and ``forward``'s horizontal part to +Y."""
    flat = forward - (forward @ up) * up
    if np.linalg.norm(flat) < 1e-6:  # looking straight up or down: any heading will do
        flat = np.eye(3)[int(np.argmin(np.abs(up)))]
        flat = flat - (flat @ up) * up
    y = _unit(flat)
    x = np.cross(y, up)
    return np.stack([x, y, up])  # rows: the new axes in old coordinates


def upright(cameras, target_distance: float = TARGET_DISTANCE) -> np.ndarray:
    """(4, 4) similarity that sets ``cameras`` (:class:`~mlx3d.cameras.Camera`, any lens) upright (module doc)."""
    from mlx3d.training.initial import look_at_centre

    cameras = list(cameras)
    if len(cameras) < 2:
        raise ValueError(f"orienting a capture needs at least 2 cameras, got {len(cameras)}")
    centres = np.array([c.center for c in cameras], np.float64)
    rotations = np.array([c.R for c in cameras], np.float64)  # world-to-camera: rows are the camera axes
    up = up_direction(centres, -rotations[:, 1])
    forward = _unit(rotations[:, 2].mean(axis=0))
    if np.linalg.norm(forward - (forward @ up) * up) < 0.3:  # every way (an orbit): the first camera's heading
        forward = rotations[0, 2]
    rot = _rotation_to_z(up, forward)
    origin = look_at_centre(cameras)
    distance = float(np.median(np.linalg.norm(centres - origin, axis=1)))
    if not distance > 0:
        raise ValueError("the cameras all sit at the point they look at: cannot choose a scale")
    scale = target_distance / distance
    m = np.eye(4)
    m[:3, :3] = scale * rot
    m[:3, 3] = -scale * rot @ origin
    return m
