"""Blender camera -> ``mlx3d.cameras.Camera``, exactly.

Resolution (with percentage), lens, sensor size and fit, shift and pixel
aspect follow Blender's own camera-parameter rules, so a world point lands on
the same pixel as ``bpy_extras.object_utils.world_to_camera_view`` says.
Perspective cameras map to 'pinhole', orthographic ones to 'orthographic'
(panoramic cameras are refused).
"""

from __future__ import annotations

import numpy as np

from mlx3d.cameras import Camera


def render_size(scene) -> tuple[int, int]:
    """Output size in pixels after the resolution percentage."""
    r = scene.render
    return int(r.resolution_x * r.resolution_percentage / 100), int(r.resolution_y * r.resolution_percentage / 100)


def camera_from_blender(camera_object, scene) -> Camera:
    """The ``Camera`` seeing what ``camera_object`` sees when ``scene`` renders."""
    cam = camera_object.data
    if cam.type not in ("PERSP", "ORTHO"):
        raise ValueError(f"camera '{camera_object.name}' is {cam.type}; only perspective and orthographic cameras are supported")
    width, height = render_size(scene)
    aspect_x, aspect_y = scene.render.pixel_aspect_x, scene.render.pixel_aspect_y
    fit = cam.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if width * aspect_x >= height * aspect_y else "VERTICAL"
        sensor = cam.sensor_width
    else:
        sensor = cam.sensor_width if fit == "HORIZONTAL" else cam.sensor_height
    pixel_aspect = aspect_y / aspect_x
    view_px = width if fit == "HORIZONTAL" else pixel_aspect * height  # pixels spanned by the sensor
    if cam.type == "PERSP":
        fx = cam.lens / sensor * view_px
        model = "pinhole"
    else:
        fx = view_px / cam.ortho_scale
        model = "orthographic"
    fy = fx / pixel_aspect
    cx = width / 2 - cam.shift_x * view_px
    cy = height / 2 + cam.shift_y * view_px / pixel_aspect
    c2w = np.array(camera_object.matrix_world, dtype=np.float64)
    c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0)  # a scaled camera object still looks the same way
    return Camera.from_opengl_c2w(c2w, width, height, fx, fy, cx, cy, near=cam.clip_start, far=cam.clip_end, model=model)
