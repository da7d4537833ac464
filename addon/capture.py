"""Capture a Blender scene as a training dataset: rendered views, their cameras, initial points and the ground-truth mesh.

``capture_dataset(out_dir, ...)`` renders the chosen mesh objects with Cycles
from an orbit of cameras around their bounding sphere (or from the scene's own
cameras) and writes, under ``out_dir``::

    images/frame_00000.png ...   RGBA 8-bit PNG, sRGB (Standard view transform),
                                 transparent background (alpha 0); with
                                 ``transparent=False`` the world background
                                 instead (alpha 255)
    transforms.json              nerfstudio format (PINHOLE; camera-to-world, OpenGL axes)
    sparse/0/cameras.txt         COLMAP text model (PINHOLE, world-to-camera,
    sparse/0/images.txt          OpenCV axes) of the same cameras and points
    sparse/0/points3D.txt        (not with ``colmap=False``)
    points3d.ply                 the initial points: x y z (float) red green blue (uchar)
    mesh.ply                     the captured objects' triangles in world space, the
                                 ground-truth geometry (e.g. to score extracted meshes):
                                 each object's own vertices and faces, modifiers applied,
                                 wound like Blender's normals (also under a mirroring
                                 transform); x y z (float), red green blue (uchar, sRGB,
                                 the mean of the vertex's corner colours), face lists

Conventions (see docs/reference/conventions.md and ``mlx3d.cameras``):

- Intrinsics come from ``addon.camera.camera_from_blender``, whose pixel frame
  has the top-left image corner at (0, 0) and pixel (row i, col j) centred at
  (j + 0.5, i + 0.5). nerfstudio (rays through ``pixel + 0.5``, then
  ``(x - cx) / fx``) and COLMAP ("the upper left image corner has coordinate
  (0, 0) and the center of the upper left most pixel has coordinate
  (0.5, 0.5)") use the same frame, so ``cx, cy`` are written unchanged; a
  centred camera has ``cx = w / 2``.
- ``transform_matrix`` is the camera's world matrix without scale: OpenGL
  camera axes (x right, y up, looking down -z), Blender world (Z up). COLMAP
  ``images.txt`` holds the inverse with OpenCV axes (x right, y down, z
  forward) as ``QW QX QY QZ TX TY TZ``.
- Frames ``i % test_every == 0`` (or the frames ``held_out`` lists) are held
  out: ``test_filenames`` and ``val_filenames`` (nerfstudio asks for the split
  it evaluates on), the rest are ``train_filenames``. COLMAP has no splits and
  ``mlx3d.datasets.load_dataset`` prefers a COLMAP model to ``transforms.json``
  (holding out every 8th image), so ``colmap=False`` leaves the
  ``transforms.json`` splits the ones a reader sees.
- Point (and mesh vertex) colours, sRGB 8-bit like the images: for each triangle's material,
  the colour input (``Base Color`` or ``Color``) of the shader node linked to
  the material output: its value when unlinked, the mesh's colour attribute
  when a Color Attribute or Attribute node feeds it (interpolated over the
  triangle), else the socket's value; the material's viewport colour when
  another shader is linked; 0.8 grey (Cycles' default surface) without a
  material. Textures are not sampled: these colours only seed training.

The user's scene is left as it was: the temporary camera is removed and every
render setting the capture changes (engine, device, resolution and percentage,
samples, denoising, transparency, file format, view transform, ...), the
active camera and the selection are restored, also on errors and cancellation.

``CaptureSession`` splits the work into ``start`` / ``step`` (one view) /
``finish`` / ``close`` so the modal operator can render one view per timer
tick and stop on Esc, keeping the frames rendered so far with a valid
``transforms.json`` and COLMAP model for them.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time

import bpy
import numpy as np
from mathutils import Matrix

from mlx3d.cameras import Camera
from mlx3d.io import atomic_write
from mlx3d.io.mesh_ply import write_mesh_ply
from mlx3d.meshing import SurfaceMesh
from mlx3d.transforms import matrix_to_quaternion

from .camera import camera_from_blender
from .scene_settings import TemporarySettings

# OpenGL camera axes (Blender) -> OpenCV camera axes (COLMAP): flip y and z.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
DEFAULT_GREY = (0.8, 0.8, 0.8)  # Cycles' surface without a material
TEMP_CAMERA_NAME = "MLX3D capture camera"
IMAGE_DIR = "images"
COLMAP_DIR = os.path.join("sparse", "0")
PLY_NAME = "points3d.ply"
MESH_NAME = "mesh.ply"


class CaptureError(ValueError):
    """The capture cannot run (no meshes, bad option, unwritable folder); the message says why."""


# ------------------------------------------------------------------ colours
def linear_to_srgb(linear) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of linear values, clipped to [0, 1]."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def srgb8(linear) -> np.ndarray:
    """Linear colours -> sRGB 8-bit (uint8)."""
    return np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)


def material_colour_source(material):
    """Where a material's surface colour comes from: ``(rgb, attribute)``.

    ``rgb`` is a linear colour; ``attribute`` is None when ``rgb`` is the
    colour, else the name of the colour attribute that feeds the shader
    (``""``: the mesh's default colour attribute), with ``rgb`` as the
    fallback when the mesh has no such attribute. Rules in the module
    docstring.
    """
    if material is None:
        return DEFAULT_GREY, None
    fallback = tuple(material.diffuse_color[:3]), None
    tree = material.node_tree
    if tree is None:
        return fallback
    outputs = [n for n in tree.nodes if n.type == "OUTPUT_MATERIAL"]
    output = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    surface = output.inputs.get("Surface") if output is not None else None
    if surface is None or not surface.is_linked:
        return fallback
    shader = surface.links[0].from_node
    socket = shader.inputs.get("Base Color") or shader.inputs.get("Color")
    if socket is None or socket.type != "RGBA":
        return fallback
    rgb = tuple(socket.default_value[:3])
    if socket.is_linked:
        source = socket.links[0].from_node
        if source.type == "VERTEX_COLOR":
            return rgb, source.layer_name
        if source.type == "ATTRIBUTE" and source.attribute_type == "GEOMETRY":
            return rgb, source.attribute_name
    return rgb, None


def _colour_attribute(mesh, name):
    """(values (K,3) linear, domain) of the mesh's colour attribute ``name`` ("": the default), or None."""
    attrs = mesh.color_attributes
    if not name:
        name = attrs.default_color_name or (attrs.active_color.name if attrs.active_color else None)
    attr = attrs.get(name) if name else None
    if attr is None or attr.domain not in ("POINT", "CORNER"):
        return None
    values = np.empty(len(attr.data) * 4, dtype=np.float32)
    attr.data.foreach_get("color", values)  # linear for byte and float colours alike
    return values.reshape(-1, 4)[:, :3].astype(np.float64), attr.domain


# ------------------------------------------------------------------ geometry
def canonical_triangles(verts, loops, mat_idx):
    """The triangles (T,3) in an order that depends only on the mesh: each one's lowest vertex index first
    (a rotation, so the winding stays) and the triangles sorted by their vertices. Blender's loop
    triangles can come in another order, and with other corners first, from one run to the next, which
    made the seeded point sample (and so the demo's result) differ between runs of the same scene."""
    first = np.argmin(verts, axis=1)
    cols = (first[:, None] + np.arange(3)) % 3
    rows = np.arange(len(verts))[:, None]
    verts, loops = verts[rows, cols], loops[rows, cols]
    order = np.lexsort((verts[:, 2], verts[:, 1], verts[:, 0]))
    return verts[order], loops[order], mat_idx[order]


class _Surfaces:
    """World-space triangles of the objects, with how to colour points on them."""

    def __init__(self, objects, depsgraph):
        tris, colour_parts, vertex_parts, face_parts = [], [], [], []
        offset = 0
        for obj in objects:
            obj_eval = obj.evaluated_get(depsgraph)
            mesh = obj_eval.to_mesh()
            try:
                mesh.calc_loop_triangles()
                n_v, n_t = len(mesh.vertices), len(mesh.loop_triangles)
                co = np.empty(n_v * 3, dtype=np.float64)
                mesh.vertices.foreach_get("co", co)
                m = np.array(obj_eval.matrix_world, dtype=np.float64)
                world = co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
                vertex_parts.append(world)
                base, offset = offset, offset + n_v
                if n_t == 0:
                    continue
                verts = np.empty(n_t * 3, dtype=np.int64)
                mesh.loop_triangles.foreach_get("vertices", verts)
                loops = np.empty(n_t * 3, dtype=np.int64)
                mesh.loop_triangles.foreach_get("loops", loops)
                mat_idx = np.empty(n_t, dtype=np.int64)
                mesh.loop_triangles.foreach_get("material_index", mat_idx)
                verts, loops = verts.reshape(-1, 3), loops.reshape(-1, 3)
                if np.linalg.det(m[:3, :3]) < 0:  # a mirroring transform turns the winding: keep the faces' normals outward
                    verts, loops = verts[:, ::-1], loops[:, ::-1]
                verts, loops, mat_idx = canonical_triangles(verts, loops, mat_idx)
                tris.append(world[verts])
                face_parts.append(verts + base)
                colour_parts.append(self._triangle_colours(obj_eval, mesh, verts, loops, mat_idx))
            finally:
                obj_eval.to_mesh_clear()
        self.vertices = np.concatenate(vertex_parts) if vertex_parts else np.zeros((0, 3))
        self.faces = np.concatenate(face_parts) if face_parts else np.zeros((0, 3), dtype=np.int64)  # (T, 3) into vertices
        self.triangles = np.concatenate(tris) if tris else np.zeros((0, 3, 3))  # (T, 3 corners, xyz)
        self.corner_colours = np.concatenate(colour_parts) if colour_parts else np.zeros((0, 3, 3))  # linear

    @staticmethod
    def _triangle_colours(obj_eval, mesh, verts, loops, mat_idx) -> np.ndarray:
        """(T, 3 corners, 3) linear colours of each triangle's corners."""
        out = np.empty(verts.shape + (3,), dtype=np.float64)
        slots = obj_eval.material_slots
        for index in np.unique(mat_idx):
            material = slots[int(index)].material if 0 <= index < len(slots) else None
            rgb, attribute = material_colour_source(material)
            rows = mat_idx == index
            found = _colour_attribute(mesh, attribute) if attribute is not None else None
            if found is not None:
                values, domain = found
                out[rows] = values[(verts if domain == "POINT" else loops)[rows]]
            else:
                out[rows] = np.asarray(rgb, dtype=np.float64)
        return out

    def mesh(self) -> SurfaceMesh:
        """The triangles as one indexed mesh: vertices used by a face, with their corners' mean colour (sRGB)."""
        used, faces = np.unique(self.faces, return_inverse=True)
        faces = faces.reshape(-1, 3)
        colour_sum = np.zeros((len(used), 3))
        np.add.at(colour_sum, faces.ravel(), self.corner_colours.reshape(-1, 3))
        corners = np.bincount(faces.ravel(), minlength=len(used))[:, None]
        colours = linear_to_srgb(colour_sum / corners)
        return SurfaceMesh(self.vertices[used].astype(np.float32), faces.astype(np.int32), colours.astype(np.float32))

    @property
    def areas(self) -> np.ndarray:
        t = self.triangles
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)

    def sample(self, count: int, seed: int):
        """``count`` points uniformly (area-weighted) on the triangles: (points (N,3) float64, colours (N,3) uint8)."""
        areas = self.areas
        rng = np.random.default_rng(seed)
        tri = rng.choice(len(areas), size=count, p=areas / areas.sum())
        u, v = rng.random(count), rng.random(count)
        fold = u + v > 1.0
        u[fold], v[fold] = 1.0 - u[fold], 1.0 - v[fold]
        w = np.stack([1.0 - u - v, u, v], axis=1)  # barycentric weights of the corners
        points = np.einsum("nk,nkc->nc", w, self.triangles[tri])
        colours = np.einsum("nk,nkc->nc", w, self.corner_colours[tri])
        return points, srgb8(colours)


def default_objects(scene, view_layer) -> list:
    """The mesh objects of the scene that are visible and render."""
    return [o for o in scene.objects if o.type == "MESH" and not o.hide_render and o.visible_get(view_layer=view_layer)]


def _resolve_objects(objects, scene, view_layer) -> list:
    if objects is None:
        found = default_objects(scene, view_layer)
        if not found:
            raise CaptureError("the scene has no visible mesh objects to capture")
        return found
    resolved = []
    for obj in objects:
        if isinstance(obj, str):
            name, obj = obj, scene.objects.get(obj)
            if obj is None:
                raise CaptureError(f"no object named '{name}' in scene '{scene.name}'")
        if obj.type != "MESH":
            raise CaptureError(f"object '{obj.name}' is {obj.type}, not a mesh; only meshes can be captured")
        resolved.append(obj)
    if not resolved:
        raise CaptureError("no mesh objects to capture")
    return resolved


def orbit_poses(centre, radius: float, num_views: int, elevations_deg) -> list:
    """OpenGL camera-to-world matrices on rings at ``elevations_deg`` around ``centre``, looking at it (world up +Z).

    Views are spread over the rings as evenly as possible (the first rings get
    the remainder) and evenly over azimuth within a ring; azimuth 0 is the
    front view (camera on -Y), rings are offset so their views interleave.
    """
    centre = np.asarray(centre, dtype=np.float64)
    rings = len(elevations_deg)
    counts = [num_views // rings + (1 if k < num_views % rings else 0) for k in range(rings)]
    poses = []
    for k, (elevation, count) in enumerate(zip(elevations_deg, counts)):
        e = math.radians(elevation)
        for j in range(count):
            a = 2.0 * math.pi * (j + k / rings) / count
            eye = centre + radius * np.array([math.cos(e) * math.sin(a), -math.cos(e) * math.cos(a), math.sin(e)])
            back = (eye - centre) / np.linalg.norm(eye - centre)  # camera +z (OpenGL looks down -z)
            right = np.cross((0.0, 0.0, 1.0), back)
            right /= np.linalg.norm(right)
            c2w = np.eye(4)
            c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, eye
            poses.append(c2w)
    return poses


def _orthonormal(camera: Camera) -> Camera:
    """``camera`` with the rotation of its pose made exactly orthonormal.

    Blender keeps matrices in float32, so a camera's rotation is orthonormal
    only to ~1e-7; the nearest rotation (polar decomposition) makes the
    camera-to-world matrix of transforms.json and the quaternion of COLMAP's
    images.txt describe exactly the same pose.
    """
    c2w = camera.to_opengl_c2w()
    u, _, vt = np.linalg.svd(c2w[:3, :3])
    c2w[:3, :3] = u @ vt
    return Camera.from_opengl_c2w(c2w, camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
                                  near=camera.near, far=camera.far, model=camera.model)


def _check_folder(out_dir, subs=(IMAGE_DIR, COLMAP_DIR)) -> str:
    """Create ``out_dir`` with its sub-folders ``subs`` and make sure files can be written there, before rendering."""
    out = os.path.abspath(os.fspath(out_dir))
    try:
        if os.path.exists(out) and not os.path.isdir(out):
            raise NotADirectoryError(20, "not a folder", out)
        for sub in subs:
            os.makedirs(os.path.join(out, sub), exist_ok=True)
            with tempfile.TemporaryFile(dir=os.path.join(out, sub)):
                pass
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise CaptureError(f"cannot write the dataset to folder {out}: {reason}" + (f" ({exc.filename})" if exc.filename and exc.filename != out else "")) from exc
    return out


def _positive(value, name, kind=int):
    try:
        v = kind(value)
    except (TypeError, ValueError):
        raise CaptureError(f"{name} must be a positive number, got {value!r}") from None
    if not (v > 0) or (kind is float and not math.isfinite(v)):
        raise CaptureError(f"{name} must be positive, got {value!r}")
    return v


# ------------------------------------------------------------------ session
class CaptureSession:
    """One capture, in steps: ``start()``, ``step()`` per view until ``done``, ``finish()``, ``close()``.

    The constructor validates everything and samples the points without
    touching the scene or the disk beyond creating the output folders (errors
    raise ``CaptureError``). ``start`` switches the render settings and adds
    the temporary camera; ``close`` (always call it; idempotent) restores the
    scene. ``finish(cancelled=...)`` writes the json, COLMAP model and points
    for the views rendered so far. Arguments as ``capture_dataset``.
    """

    def __init__(self, out_dir, *, objects=None, use_scene_cameras=False, num_views=72, radius=None,
                 elevations_deg=(-10.0, 20.0, 45.0), resolution=(256, 256), samples=32, num_points=20000,
                 test_every=8, held_out=None, transparent=True, colmap=True, seed=0, scene=None, view_layer=None):
        self.t0 = time.perf_counter()
        self.scene = scene or bpy.context.scene
        if view_layer is None:
            view_layer = bpy.context.view_layer if self.scene == bpy.context.scene else self.scene.view_layers[0]
        self.view_layer = view_layer
        if len(tuple(resolution)) != 2:
            raise CaptureError(f"resolution must be (width, height), got {resolution!r}")
        self.width, self.height = (_positive(r, "resolution", int) for r in resolution)
        self.samples = _positive(samples, "samples", int)
        self.num_points = _positive(num_points, "num_points", int)
        self.test_every = int(test_every)
        if self.test_every < 0:
            raise CaptureError(f"test_every must be 0 (no held-out frames) or positive, got {test_every!r}")
        self.held_out = None if held_out is None else sorted({int(i) for i in held_out})
        self.transparent = bool(transparent)
        self.colmap = bool(colmap)
        self.seed = int(seed)
        self.use_scene_cameras = bool(use_scene_cameras)
        self.objects = _resolve_objects(objects, self.scene, self.view_layer)
        self.notes: list = []

        surfaces = _Surfaces(self.objects, self.view_layer.depsgraph)
        names = ", ".join(f"'{o.name}'" for o in self.objects)
        if len(surfaces.triangles) == 0 or surfaces.areas.sum() <= 0.0:
            raise CaptureError(f"the mesh objects {names} have no faces with area to capture")
        lo, hi = surfaces.vertices.min(axis=0), surfaces.vertices.max(axis=0)
        self.centre = (lo + hi) / 2.0
        self.bound_radius = float(np.linalg.norm(surfaces.vertices - self.centre, axis=1).max())
        if not self.bound_radius > 0.0:
            raise CaptureError(f"the mesh objects {names} have no extent")

        if self.use_scene_cameras:
            self.cameras = sorted((o for o in self.scene.objects if o.type == "CAMERA"), key=lambda o: o.name)
            if not self.cameras:
                raise CaptureError(f"use_scene_cameras: scene '{self.scene.name}' has no camera objects")
            for cam in self.cameras:
                if cam.data.type != "PERSP":
                    raise CaptureError(f"camera '{cam.name}' is {cam.data.type}; only perspective cameras can be captured")
            self.poses = None
            self.radius = None
            self.total = len(self.cameras)
        else:
            num_views = _positive(num_views, "num_views", int)
            elevations = [float(e) for e in elevations_deg]
            if not elevations:
                raise CaptureError("elevations_deg needs at least one ring")
            bad = [e for e in elevations if not -90.0 < e < 90.0]
            if bad:
                raise CaptureError(f"elevations must lie strictly between -90 and 90 degrees, got {bad}")
            self.radius = 2.2 * self.bound_radius if radius is None else _positive(radius, "radius", float)
            if self.radius <= 1.05 * self.bound_radius:
                raise CaptureError(
                    f"radius {self.radius:.4g} puts the cameras inside (or at) the objects' bounding sphere "
                    f"(radius {self.bound_radius:.4g}); use more than {1.05 * self.bound_radius:.4g}"
                )
            self.poses = orbit_poses(self.centre, self.radius, num_views, elevations)
            self.cameras = None
            self.total = len(self.poses)
        if self.held_out and not 0 <= self.held_out[0] <= self.held_out[-1] < self.total:
            raise CaptureError(f"held_out frames must be indices 0 to {self.total - 1}, got {self.held_out}")

        self.out_dir = _check_folder(out_dir, (IMAGE_DIR, COLMAP_DIR) if self.colmap else (IMAGE_DIR,))
        self.points, self.colours = surfaces.sample(self.num_points, self.seed)
        self.mesh = surfaces.mesh()
        if self.scene.world is None and not any(o.type == "LIGHT" and not o.hide_render for o in self.scene.objects):
            self.notes.append("the scene has no world and no lights: surfaces that do not emit light render black")

        self.frames: list = []  # (file name, mlx3d Camera)
        self._settings = TemporarySettings()
        self._temp_camera = None
        self._selection = None
        self._started = False
        self._closed = False

    # -- scene state
    def _set(self, owner, attr, value) -> None:
        self._settings.set(owner, attr, value)

    def start(self) -> None:
        """Switch the render settings for the capture and add the temporary camera."""
        if self._started:
            return
        self._started = True
        scene, render = self.scene, self.scene.render
        self._selection = ([o for o in self.view_layer.objects if o.select_get(view_layer=self.view_layer)], self.view_layer.objects.active)
        self._settings.keep(scene, "camera")  # the views set it
        for attr, value in [("engine", "CYCLES"), ("resolution_x", self.width), ("resolution_y", self.height),
                            ("resolution_percentage", 100), ("pixel_aspect_x", 1.0), ("pixel_aspect_y", 1.0),
                            ("film_transparent", self.transparent), ("use_border", False), ("use_compositing", False),
                            ("use_sequencer", False), ("use_single_layer", True), ("use_multiview", False),
                            ("use_motion_blur", False), ("use_persistent_data", True), ("dither_intensity", 0.0)]:
            self._set(render, attr, value)
        image = render.image_settings
        if hasattr(image, "media_type"):
            self._set(image, "media_type", "IMAGE")
        for attr, value in [("file_format", "PNG"), ("color_mode", "RGBA"), ("color_depth", "8"), ("color_management", "FOLLOW_SCENE")]:
            self._set(image, attr, value)
        cycles = scene.cycles
        for attr, value in [("device", "CPU"), ("samples", self.samples), ("use_denoising", False), ("use_adaptive_sampling", False)]:
            self._set(cycles, attr, value)
        view = scene.view_settings
        for attr, value in [("view_transform", "Standard"), ("look", "None"), ("exposure", 0.0), ("gamma", 1.0), ("use_curve_mapping", False)]:
            self._set(view, attr, value)
        self._set(scene.display_settings, "display_device", "sRGB")
        if self.poses is not None:
            data = bpy.data.cameras.new(TEMP_CAMERA_NAME)
            obj = bpy.data.objects.new(TEMP_CAMERA_NAME, data)
            self._temp_camera = (obj, data)
            scene.collection.objects.link(obj)
            # Field of view: the bounding sphere fills the shorter image side with a 10 % margin.
            half = min(math.asin(self.bound_radius / self.radius) * 1.1, math.radians(80.0))
            data.sensor_fit = "HORIZONTAL" if self.width <= self.height else "VERTICAL"
            data.sensor_width = data.sensor_height = 36.0
            data.lens = 18.0 / math.tan(half)
            data.clip_start = max(1e-4, 0.1 * (self.radius - self.bound_radius))
            data.clip_end = max(1000.0, 100.0 * self.radius)

    @property
    def done(self) -> bool:
        return len(self.frames) >= self.total

    def step(self) -> int:
        """Render the next view; returns how many views are done."""
        if not self._started:
            self.start()
        if self.done:
            return len(self.frames)
        i = len(self.frames)
        scene = self.scene
        if self.poses is not None:
            cam_obj = self._temp_camera[0]
            cam_obj.matrix_world = Matrix(self.poses[i].tolist())
        else:
            cam_obj = self.cameras[i]
        scene.camera = cam_obj
        self.view_layer.update()
        camera = _orthonormal(camera_from_blender(cam_obj, scene))
        name = f"frame_{i:05d}.png"
        path = os.path.join(self.out_dir, IMAGE_DIR, name)
        tmp = os.path.join(self.out_dir, IMAGE_DIR, f".{name}.{os.getpid()}.tmp.png")
        try:
            if bpy.ops.render.render(scene=scene.name) != {"FINISHED"}:
                raise CaptureError(f"rendering view {i + 1} of {self.total} failed")
            # save_render applies the scene's output settings; no '#' frame-number substitution in the path.
            bpy.data.images["Render Result"].save_render(filepath=tmp, scene=scene)
            os.replace(tmp, path)  # a frame file is always a whole image
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)
        self.frames.append((name, camera))
        return len(self.frames)

    def close(self) -> None:
        """Restore the scene as it was before ``start`` (idempotent)."""
        if self._closed:
            return
        self._closed = True
        errors = self._settings.restore()
        if self._temp_camera is not None:
            obj, data = self._temp_camera
            self._temp_camera = None
            bpy.data.objects.remove(obj, do_unlink=True)
            bpy.data.cameras.remove(data, do_unlink=True)
        if self._selection is not None:
            selected, active = self._selection
            for obj in self.view_layer.objects:
                obj.select_set(obj in selected, view_layer=self.view_layer)
            self.view_layer.objects.active = active
        if errors:
            raise CaptureError("could not restore some render settings: " + "; ".join(errors))

    # -- output
    def finish(self, cancelled: bool = False):
        """Write transforms.json, the COLMAP model and the points for the views rendered so far.

        Returns (info dict, messages); with no view rendered nothing is written.
        """
        n = len(self.frames)
        seconds = time.perf_counter() - self.t0
        info = {
            "out_dir": self.out_dir, "frames": n, "planned": self.total, "cancelled": bool(cancelled),
            "width": self.width, "height": self.height, "num_points": 0, "centre": self.centre.tolist(),
            "bound_radius": self.bound_radius, "radius": self.radius, "train_filenames": [], "test_filenames": [],
            "seconds": seconds,
        }
        if n == 0:
            return info, [f"capture cancelled before any view was rendered; nothing written to {self.out_dir}"] + self.notes
        names = [f"{IMAGE_DIR}/{name}" for name, _ in self.frames]
        if self.held_out is not None:
            test = [names[i] for i in self.held_out if i < n]
        else:
            test = [names[i] for i in range(n) if self.test_every and i % self.test_every == 0]
        train = [p for p in names if p not in set(test)]
        info.update(train_filenames=train, test_filenames=test, num_points=len(self.points))
        self._write_points()
        write_mesh_ply(os.path.join(self.out_dir, MESH_NAME), self.mesh.vertices, self.mesh.faces, self.mesh.colors)
        if self.colmap:
            self._write_colmap()
        info.update(self._write_transforms(names, train, test))
        info["seconds"] = time.perf_counter() - self.t0
        stale = self._stale_frames()
        what = ", ".join(f"'{o.name}'" for o in self.objects)
        head = (f"captured {n} of {self.total} views (cancelled)" if cancelled else f"captured {n} views") + (
            f" of {what} at {self.width}x{self.height} ({self.samples} samples) with {len(self.points):,} points "
            f"into {self.out_dir} in {info['seconds']:.1f} s"
        )
        notes = list(self.notes)
        if stale:
            notes.append(f"{len(stale)} older frame files in {IMAGE_DIR}/ are not part of this capture (e.g. {stale[0]})")
        return info, [head] + notes

    def _stale_frames(self) -> list:
        ours = {name for name, _ in self.frames}
        folder = os.path.join(self.out_dir, IMAGE_DIR)
        return sorted(f for f in os.listdir(folder) if f.startswith("frame_") and f.endswith(".png") and f not in ours)

    @staticmethod
    def _intrinsics(camera) -> dict:
        return {"fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy, "w": camera.width, "h": camera.height}

    def _write_transforms(self, names, train, test) -> dict:
        intrinsics = [self._intrinsics(cam) for _, cam in self.frames]
        shared = all(k == intrinsics[0] for k in intrinsics)
        meta = {"camera_model": "PINHOLE"}  # Blender renders without lens distortion
        if shared:
            meta.update(intrinsics[0])
        frames = []
        for path, (_, cam), k in zip(names, self.frames, intrinsics):
            frame = {"file_path": path, "transform_matrix": cam.to_opengl_c2w().tolist()}
            if not shared:
                frame.update(k)
            frames.append(frame)
        meta.update({"frames": frames, "ply_file_path": PLY_NAME, "train_filenames": train, "val_filenames": test, "test_filenames": test})
        path = os.path.join(self.out_dir, "transforms.json")
        with atomic_write(path, "w", encoding="utf-8") as f:
            json.dump(meta, f, indent=2)
        return {k: intrinsics[0][k] for k in ("fl_x", "fl_y", "cx", "cy")} if shared else {}

    def _write_points(self) -> None:
        vertex = np.empty(len(self.points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
        for i, axis in enumerate("xyz"):
            vertex[axis] = self.points[:, i]
        for i, channel in enumerate(("red", "green", "blue")):
            vertex[channel] = self.colours[:, i]
        header = (
            "ply\nformat binary_little_endian 1.0\ncomment initial points sampled on the captured surfaces\n"
            f"element vertex {len(vertex)}\nproperty float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
        )
        with atomic_write(os.path.join(self.out_dir, PLY_NAME)) as f:
            f.write(header.encode("ascii"))
            f.write(vertex.tobytes())

    def _write_colmap(self) -> None:
        folder = os.path.join(self.out_dir, COLMAP_DIR)
        camera_ids: dict = {}
        for _, cam in self.frames:
            camera_ids.setdefault((cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy), len(camera_ids) + 1)
        lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                 f"# Number of cameras: {len(camera_ids)}"]
        for (w, h, fx, fy, cx, cy), cid in camera_ids.items():
            lines.append(f"{cid} PINHOLE {w} {h} {fx!r} {fy!r} {cx!r} {cy!r}")
        with atomic_write(os.path.join(folder, "cameras.txt"), "w", encoding="utf-8") as f:
            f.write("\n".join(lines) + "\n")

        lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {len(self.frames)}, mean observations per image: 0"]
        for i, (name, cam) in enumerate(self.frames):
            w2c = cam.viewmat  # world-to-camera, OpenCV axes
            q = matrix_to_quaternion(w2c[:3, :3])
            t = w2c[:3, 3]
            cid = camera_ids[(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)]
            lines.append(" ".join([str(i + 1)] + [repr(float(v)) for v in (*q, *t)] + [str(cid), name]))
            lines.append("")  # no 2D observations
        with atomic_write(os.path.join(folder, "images.txt"), "w", encoding="utf-8") as f:
            f.write("\n".join(lines) + "\n")

        with atomic_write(os.path.join(folder, "points3D.txt"), "w", encoding="utf-8") as f:
            f.write("# 3D point list with one line of data per point:\n"
                    "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                    f"# Number of points: {len(self.points)}, mean track length: 0\n")
            p = self.points.astype(np.float32)
            c = self.colours
            f.write("".join(
                f"{i + 1} {p[i, 0]:.9g} {p[i, 1]:.9g} {p[i, 2]:.9g} {c[i, 0]} {c[i, 1]} {c[i, 2]} 0\n" for i in range(len(p))
            ))


def capture_dataset(out_dir, *, objects=None, use_scene_cameras=False, num_views=72, radius=None,
                    elevations_deg=(-10.0, 20.0, 45.0), resolution=(256, 256), samples=32, num_points=20000,
                    test_every=8, held_out=None, transparent=True, colmap=True, seed=0, progress=None, scene=None):
    """Render ``objects`` from many views into a training dataset under ``out_dir``; returns (info, messages).

    objects: mesh objects (or names) to frame and sample points on (default:
        every visible mesh that renders). Everything else that renders in the
        scene also appears in the images (hide it from rendering to leave it
        out).
    use_scene_cameras: render from the scene's camera objects (sorted by
        name, perspective only) instead of an orbit; ``num_views``, ``radius``
        and ``elevations_deg`` are then unused.
    num_views: orbit views, spread over the rings at ``elevations_deg``
        (degrees, strictly between -90 and 90) and evenly in azimuth, all
        looking at the centre of the objects' bounding sphere from distance
        ``radius`` (default 2.2 x its radius); the field of view fits the
        sphere with a 10 % margin.
    resolution: (width, height) in pixels (scene cameras too); samples: Cycles samples per pixel
        (CPU, denoiser off, fixed seed); num_points: points sampled on the
        surfaces (area-weighted, ``seed``); test_every: hold out every n-th
        frame (0: none); progress: ``progress(done, total)`` after each view.
    held_out: indices of the frames to hold out (in render order: the orbit's,
        or the scene cameras' sorted by name) instead of every
        ``test_every``-th; ``()`` holds out none.
    transparent: render the background transparent (alpha 0, the default);
        False renders the world background into the images (alpha 255), as
        a photo of a scene whose surroundings must be reconstructed too.
    colmap: also write the COLMAP model under ``sparse/0`` (the default).
        ``mlx3d.datasets.load_dataset`` reads a folder with one as COLMAP,
        which has no splits; False leaves ``transforms.json`` and its
        ``held_out`` / ``test_every`` splits as the dataset.

    The info dict holds ``out_dir``, ``frames``, ``planned``, ``cancelled``,
    ``width``, ``height``, the shared ``fl_x fl_y cx cy``, ``num_points``,
    ``centre``, ``bound_radius``, ``radius``, ``train_filenames``,
    ``test_filenames`` and ``seconds``. Raises ``CaptureError`` before
    rendering for bad input; Ctrl+C (KeyboardInterrupt) keeps the views
    rendered so far with their metadata. The scene is always restored.
    """
    session = CaptureSession(
        out_dir, objects=objects, use_scene_cameras=use_scene_cameras, num_views=num_views, radius=radius,
        elevations_deg=elevations_deg, resolution=resolution, samples=samples, num_points=num_points,
        test_every=test_every, held_out=held_out, transparent=transparent, colmap=colmap, seed=seed, scene=scene,
    )
    try:
        session.start()
        while not session.done:
            done = session.step()
            if progress is not None:
                progress(done, session.total)
    except KeyboardInterrupt:
        session.close()
        session.finish(cancelled=True)
        raise
    finally:
        session.close()
    return session.finish()
