"""Blender camera <-> ``mlx3d.cameras.Camera``, exactly.

Resolution (with percentage), lens, sensor size and fit, shift and pixel
aspect follow Blender's own camera-parameter rules, so a world point lands on
the same pixel as ``bpy_extras.object_utils.world_to_camera_view`` says.
Perspective cameras map to 'pinhole', orthographic ones to 'orthographic'
(panoramic cameras are refused). ``set_blender_camera`` is the inverse:
``camera_from_blender`` of the camera it sets gives the ``Camera`` back when
the scene renders at the camera's size with square pixels.
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


#: Sensor size (mm) of the cameras ``set_blender_camera`` sets: Blender's default, a full-frame width.
SENSOR_MM = 36.0


def set_blender_camera(camera_object, camera: Camera) -> list[str]:
    """Pose and lens of the Blender camera ``camera_object`` so that it sees what ``camera`` sees.

    The inverse of ``camera_from_blender`` for a scene rendering at
    ``camera.width`` x ``camera.height`` with square pixels: the world matrix
    is the camera-to-world pose in OpenGL axes (Blender's camera axes: x
    right, y up, looking down -z); the sensor (``SENSOR_MM``) fits the longer
    image side, the lens is fx in millimetres on it and the shift is the
    principal point's offset from the centre. Returns notes on what a Blender
    camera cannot hold: lens distortion (dropped) and fy != fx (fx kept).
    """
    if camera.model not in ("pinhole", "opencv", "orthographic"):
        raise ValueError(f"a {camera.model} camera has no Blender equivalent; only pinhole, opencv and orthographic cameras are supported")
    from mathutils import Matrix

    width, height = camera.width, camera.height
    fit = "HORIZONTAL" if width >= height else "VERTICAL"
    view_px = width if fit == "HORIZONTAL" else height  # pixels spanned by the sensor
    data = camera_object.data
    data.sensor_fit = fit
    data.sensor_width = data.sensor_height = SENSOR_MM
    if camera.model == "orthographic":
        data.type = "ORTHO"
        data.ortho_scale = view_px / camera.fx
    else:
        data.type = "PERSP"
        data.lens = camera.fx * SENSOR_MM / view_px
    data.shift_x = (width / 2 - camera.cx) / view_px
    data.shift_y = (camera.cy - height / 2) / view_px
    camera_object.matrix_world = Matrix(camera.to_opengl_c2w().tolist())
    notes = []
    if camera.model == "opencv" and any(camera.dist):
        notes.append("lens distortion")
    if abs(camera.fy - camera.fx) > 1e-6 * camera.fx:
        notes.append("vertical focal length (fy != fx)")
    return notes
