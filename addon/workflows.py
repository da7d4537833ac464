"""What the add-on does, as plain functions on Blender objects.

Operators and the headless script both call these; each returns what it made
and a list of messages for the user: the first says what was done, the rest
are caveats (dropped rows, zero-filled properties, attributes left out of a
file). Errors are raised as ``ValueError``
subclasses with a message naming the object, file or value at fault, before
anything in the scene or on disk is changed.
"""

from __future__ import annotations

import os
import time
import warnings
from contextlib import contextmanager

import bpy
import numpy as np

from mlx3d.floaters import radius_outliers, statistical_outliers
from mlx3d.io import FORMATS, detect_format, format_for_path
from mlx3d.io import read_splats as read_splat_file
from mlx3d.io import write_splats as write_splat_file
from mlx3d.meshing import DEFAULT_TRIM, MeshingError, SurfaceMesh, keep_large_components, reconstruct_surface, simplify
from mlx3d.splatting import GaussianModel, merge_splats

from .camera import camera_from_blender
from .display import node_material
from .splat_object import (
    SplatObjectError,
    baked_splats,
    create_splat_object,
    is_identity,
    has_splat_attributes,
    is_splat_object,
    object_matrix,
    read_splats,
    replace_splats,
    srgb_to_linear,
)
from .worker import WorkerJob

# Axis presets: file axes -> Blender axes, exact 0/±1 matrices.
AXIS_PRESETS = {
    "NONE": np.eye(4),
    "Y_UP": np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64),
    "Y_DOWN": np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64),
}
AXIS_ITEMS = [
    ("NONE", "Keep as is", "Use the file's coordinates unchanged"),
    ("Y_UP", "Y-up to Z-up", "Files whose up axis is +Y (many viewers and engines)"),
    ("Y_DOWN", "Y-down to Z-up", "Files from COLMAP-based trainers (Y down, Z forward)"),
]


@contextmanager
def _warnings_into(messages: list):
    """Turn Python warnings raised by mlx3d inside the block into user messages."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    messages.extend(str(w.message) for w in caught)


def axis_matrix(axis: str) -> np.ndarray:
    try:
        return AXIS_PRESETS[axis]
    except KeyError:
        raise ValueError(f"unknown axis preset {axis!r}; choose one of {sorted(AXIS_PRESETS)}") from None


def splat_objects(objects) -> list:
    """The splat objects among ``objects``, in the given order. A point cloud with only some of
    the splat attributes raises ``SplatObjectError`` naming what it lacks."""
    found = []
    for obj in objects:
        if is_splat_object(obj):
            found.append(obj)
        elif has_splat_attributes(obj):
            read_splats(obj)  # raises, naming the missing attributes
    return found


def file_stem(path) -> str:
    """An object name for a splat file: its name without the format's extension
    (``scan.compressed.ply`` -> ``scan``; an unbundled SOG ``meta.json`` -> its folder's name)."""
    path = os.path.abspath(os.fspath(path))
    base = os.path.basename(path)
    for fmt in FORMATS:
        for ext in fmt.extensions:
            if base.lower().endswith(ext):
                return base[:-len(ext)] or os.path.basename(os.path.dirname(path))
    return os.path.splitext(base)[0]


def import_splat_file(path, *, sh_degree=None, drop_nonfinite=False, axis="NONE", location=None, collection=None):
    """Import one splat file of any format ``mlx3d.io.read_splats`` reads
    (PLY, compressed PLY, SPZ, .splat, .ksplat, SOG, glTF; recognised by
    content) as a splat object named after it.

    sh_degree: cap (truncate/pad) or None for the file's degree; drop_nonfinite:
    drop rows with NaN/Inf (counted in the messages) instead of refusing the
    file; axis: an ``AXIS_PRESETS`` key applied as the object's transform;
    location: world position of the object origin (e.g. the 3D cursor).
    Returns (object, messages). A bad file raises ``SplatFormatError`` and
    leaves the scene untouched.
    """
    matrix = axis_matrix(axis).copy()
    notes: list = []
    fmt = detect_format(path)
    with _warnings_into(notes):
        arrays = read_splat_file(path, format=fmt.name, sh_degree=sh_degree, nonfinite="drop" if drop_nonfinite else "error")
    if location is not None:
        matrix[:3, 3] = np.asarray(location, dtype=np.float64)
    obj, messages = create_splat_object(file_stem(path), arrays, collection=collection, matrix=None if is_identity(matrix) else matrix)
    return obj, [f"imported {arrays.count:,} splats (SH degree {arrays.sh_degree}) from {os.path.basename(os.fspath(path))} "
                 f"({fmt.description})"] + notes + messages


def export_splat_file(path, objects, *, axis="NONE", sh_degree=None):
    """Write the splat objects, each with its world transform baked in, into one file.

    The extension of ``path`` picks the format (``.ply``, ``.compressed.ply``,
    ``.spz``, ``.sog``, ``.splat``, ``.glb``; see ``mlx3d.io.write_splats``).
    axis: the inverse of an ``AXIS_PRESETS`` key is applied (so a file imported
    with a preset exports back to its own axes). Returns (count, messages).
    """
    fmt = format_for_path(path, writable=True)
    objects = splat_objects(objects)
    if not objects:
        raise SplatObjectError("no splat objects to export (select point clouds imported as Gaussian splats)")
    bpy.context.view_layer.update()  # matrix_world is stale until the view layer updates
    to_file = np.linalg.inv(axis_matrix(axis))
    parts, messages = [], []
    for obj in objects:
        arrays, warnings = baked_splats(obj, to_file @ object_matrix(obj))
        parts.append(arrays)
        messages += warnings
    with _warnings_into(messages):
        merged = parts[0] if len(parts) == 1 and sh_degree is None else merge_splats(parts, sh_degree)
        write_splat_file(path, merged, format=fmt.name)
    names = ", ".join(obj.name for obj in objects)
    return merged.count, [f"exported {merged.count:,} splats from {names} to {os.path.basename(os.fspath(path))} "
                          f"({fmt.description})"] + messages


def merge_objects(objects, name="Merged splats", collection=None):
    """A new splat object (identity transform) holding all given splat objects, transforms baked."""
    objects = splat_objects(objects)
    if len(objects) < 2:
        raise SplatObjectError(f"merge needs at least two splat objects, got {len(objects)}")
    bpy.context.view_layer.update()
    parts, messages = [], []
    for obj in objects:
        arrays, warnings = baked_splats(obj)
        parts.append(arrays)
        messages += warnings
    with _warnings_into(messages):
        merged = merge_splats(parts)
    obj, more = create_splat_object(name, merged, collection=collection or objects[0].users_collection[0])
    return obj, [f"merged {len(objects)} objects into '{obj.name}' ({merged.count:,} splats)"] + messages + more


def apply_transform(obj):
    """Bake the object's own transform (``matrix_basis``) into its splats and reset it, like Ctrl+A."""
    basis = object_matrix(obj, "basis")
    if is_identity(basis):
        return [f"'{obj.name}' has no transform to apply"]
    arrays, warnings = baked_splats(obj, basis)
    warnings += replace_splats(obj, arrays)
    obj.matrix_basis.identity()
    return [f"applied the transform of '{obj.name}' to {arrays.count:,} splats"] + warnings


def _keep_rows(obj, keep: np.ndarray, what: str):
    arrays, warnings = read_splats(obj)
    removed = int((~keep).sum())
    if removed == 0:
        return 0, [f"{what}: nothing removed from '{obj.name}'"]
    if not keep.any():
        raise SplatObjectError(f"{what} would remove all {arrays.count:,} splats of '{obj.name}'; nothing was changed")
    model = GaussianModel.from_arrays(arrays).select(keep)
    warnings += replace_splats(obj, model.to_arrays())
    return removed, [f"{what}: removed {removed:,} of {arrays.count:,} splats from '{obj.name}'"] + warnings


def world_positions(obj) -> np.ndarray:
    """(N,3) float64 splat centres in world space."""
    bpy.context.view_layer.update()
    means = read_splats(obj)[0].means.astype(np.float64)
    m = object_matrix(obj)
    return means @ m[:3, :3].T + m[:3, 3]


def box_extent(box, what="crop box"):
    """(lo (3,), hi (3,)) in ``box``'s own frame: a mesh's bounding box or an empty's cube."""
    if box.type == "EMPTY":
        size = box.empty_display_size
        return np.full(3, -size), np.full(3, size)
    if box.type == "MESH":
        corners = np.array([list(c) for c in box.bound_box], dtype=np.float64)
        return corners.min(axis=0), corners.max(axis=0)
    raise SplatObjectError(f"{what} '{box.name}' must be a mesh or an empty, not {box.type}")


def placed_bounds(lo, hi, matrix) -> np.ndarray:
    """(2, 3) min and max corners of the axis-aligned box around the box ``lo``..``hi`` (3,) moved by the affine
    ``matrix`` (4, 4): exact for a matrix that only moves, scales or turns by multiples of 90 degrees."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], dtype=np.float64)
    placed = corners @ np.asarray(matrix)[:3, :3].T + np.asarray(matrix)[:3, 3]
    return np.stack([placed.min(axis=0), placed.max(axis=0)])


def box_world_bounds(box, what="box") -> np.ndarray:
    """(2, 3) min and max world corners of the box object ``box`` (``box_extent``) as placed in the scene
    (``placed_bounds``)."""
    lo, hi = box_extent(box, what)
    bpy.context.view_layer.update()  # matrix_world is stale until the view layer updates
    return placed_bounds(lo, hi, object_matrix(box))


def crop_to_box(obj, box, *, keep_inside=True):
    """Keep (or delete) the splats inside the bounds of ``box`` (a mesh's bounding box or an empty's cube)."""
    if box is None or box == obj:
        raise SplatObjectError("choose a mesh or empty (other than the splat object) as the crop box")
    lo, hi = box_extent(box)
    local = world_positions(obj)
    to_box = np.linalg.inv(object_matrix(box))
    local = local @ to_box[:3, :3].T + to_box[:3, 3]
    inside = np.all((local >= lo) & (local <= hi), axis=1)
    keep = inside if keep_inside else ~inside
    return _keep_rows(obj, keep, f"crop to '{box.name}'")


def remove_floaters(obj, *, method="STATISTICAL", k=25, std_ratio=10.5, radius=0.05, min_neighbours=4, progress=None):
    """Remove floaters (see ``mlx3d.floaters``) measured on world-space centres."""
    points = world_positions(obj).astype(np.float32)
    if method == "STATISTICAL":
        result = statistical_outliers(points, k=k, std_ratio=std_ratio, progress=progress)
    elif method == "RADIUS":
        result = radius_outliers(points, radius=radius, min_neighbours=min_neighbours, progress=progress)
    else:
        raise ValueError(f"unknown floater method {method!r}; use 'STATISTICAL' or 'RADIUS'")
    return _keep_rows(obj, result.keep, "remove floaters")


def ply_size_bytes(arrays) -> int:
    """Size of the PLY file ``write_splat_ply`` would write for ``arrays`` (header excluded)."""
    standard = 3 + 3 + 3 + 3 * arrays.sh_rest.shape[1] + 1 + 3 + 4
    extra = sum(v.dtype.itemsize for name, v in arrays.extra.items() if name not in ("nx", "ny", "nz"))
    return arrays.count * (4 * standard + extra)


def compact_object(obj, *, max_gaussians=None, min_opacity=0.0, sh_degree=None):
    """Compact the object's splats in place (see ``GaussianModel.compact``); reports counts and sizes."""
    arrays, warnings = read_splats(obj)
    before = ply_size_bytes(arrays)
    out = GaussianModel.from_arrays(arrays).compact(min_opacity=min_opacity, max_gaussians=max_gaussians, target_sh_degree=sh_degree).to_arrays()
    warnings += replace_splats(obj, out)
    after = ply_size_bytes(out)
    return [
        f"compact '{obj.name}': {arrays.count:,} -> {out.count:,} splats, SH degree {arrays.sh_degree} -> {out.sh_degree}, "
        f"PLY {before / 1e6:.1f} MB -> {after / 1e6:.1f} MB"
    ] + warnings


def splat_info(obj) -> dict:
    """Count, SH degree, memory of the raw attributes and world bounds of a splat object."""
    arrays, _ = read_splats(obj)
    world = world_positions(obj)
    return {
        "count": arrays.count,
        "sh_degree": arrays.sh_degree,
        "memory_bytes": ply_size_bytes(arrays),
        "bounds_min": world.min(axis=0).tolist() if arrays.count else None,
        "bounds_max": world.max(axis=0).tolist() if arrays.count else None,
    }


# ------------------------------------------------------------------ surface mesh
MESH_MATERIAL = "MLX3D Mesh"
MESH_COLOR_ATTRIBUTE = "Color"
#: How ``MeshExtraction`` meshes: (identifier, label, description), as the operator and the panel show them.
MESH_METHOD_ITEMS = [
    ("FUSION", "Depth fusion", "Depth rendered from views of the splats, fused into a signed distance volume; "
     "space no view saw is left empty (open where unseen, no invented surface)"),
    ("POISSON", "Poisson", "A closed surface through the splats read as oriented discs (Poisson reconstruction); "
     "fills unseen parts"),
]
MESH_METHODS = tuple(item[0].lower() for item in MESH_METHOD_ITEMS)
#: Splats less opaque than this are skipped by the rasterizer, so fusion cannot see them.
_VISIBLE_OPACITY = 1.0 / 255.0


class ExtractionCancelled(Exception):
    """Raised through the meshing progress callback to stop an extraction; nothing is added to the scene."""


def _render_cameras(cameras, scene) -> list:
    """``mlx3d.cameras.Camera`` (world frame) of ``cameras``: Blender camera objects or Cameras, in order."""
    from mlx3d.cameras import Camera

    out = []
    for cam in cameras:
        if isinstance(cam, Camera):
            out.append(cam)
        elif getattr(cam, "type", None) == "CAMERA":
            out.append(camera_from_blender(cam, scene))
        else:
            what = f"'{cam.name}' ({cam.type.lower()} object)" if hasattr(cam, "name") and hasattr(cam, "type") else repr(cam)
            raise MeshingError(f"{what} is not a camera: the mesh is rendered from camera objects")
    return out


class MeshExtraction(WorkerJob):
    """One surface-mesh extraction from a splat object.

    - The constructor (main thread) checks the object and the options and reads
      the splats; bad input raises here, before the long part. ``method``
      ``'fusion'`` puts them in world space (the object's world matrix, any
      affine) and picks the cameras; ``'poisson'`` turns them into oriented
      surfels in the object's frame (``GaussianModel.surfel_samples``).
    - Fusion only: ``render_next()`` renders the depth and colour of one view
      (MLX, so on the main thread); ``views_left`` counts those still to render.
    - ``compute(progress)`` renders what is left (main thread) and meshes:
      ``mlx3d.meshing.fuse_depth_maps`` of the views, brought back to the
      object's frame, or ``reconstruct_surface`` of the surfels; then drops
      pieces under ``cleanup`` times the largest (``keep_large_components``)
      and, with ``faces``, simplifies to at most that many (``simplify``).
      ``start()`` runs it on a worker thread once every view is rendered
      (``work()`` refuses otherwise); ``running`` and ``progress`` (done,
      total; fusion: one per view rendered, then two per view fused, total 3 x
      views) follow it; ``cancel()`` stops it at its next progress report.
    - ``add_object()`` (main thread) builds the mesh object from the result,
      or raises the error the computation raised. Nothing is added before it.

    Options as ``extract_mesh``.
    """

    def __init__(self, obj, *, method="fusion", cameras=None, resolution=128, cleanup=0.01, faces=0, min_opacity=0.01,
                 max_points=200000, trim=None, camera_centres=None, name=None, collection=None, padding=0.1, bounds=None):
        if obj is None or not is_splat_object(obj):
            what = "no active object" if obj is None else f"'{obj.name}' is not a splat object"
            raise SplatObjectError(f"{what}: choose a point cloud imported as Gaussian splats to extract a mesh from")
        self.t0 = time.perf_counter()
        self.source, self.source_name = obj, obj.name
        self.method = str(method).lower()
        if self.method not in MESH_METHODS:
            raise MeshingError(f"unknown mesh method {method!r}; use one of {', '.join(MESH_METHODS)}")
        self.name = name or f"{obj.name} mesh"
        self.collection = collection
        self.resolution = int(resolution)
        self.cleanup = float(cleanup or 0.0)
        if not 0.0 <= self.cleanup <= 1.0:
            raise MeshingError(f"cleanup must be a fraction in [0, 1], got {cleanup!r}")
        self.faces = int(faces or 0)
        if self.faces != (faces or 0) or self.faces < 0:
            raise MeshingError(f"faces must be a whole number of triangles (0: as extracted), got {faces!r}")
        if len(obj.data.points) == 0:
            raise MeshingError(f"'{obj.name}' holds no splats; nothing to mesh")
        self.bounds = None
        if bounds is not None:
            if self.method != "fusion":
                raise MeshingError("bounds set the volume of fusion; Poisson meshes every splat (crop the splats to a box first)")
            self.bounds = np.asarray(bounds, dtype=np.float64)
            if self.bounds.size != 6:
                raise MeshingError(f"bounds must be two world corners (min, max) of 3 coordinates each, got {self.bounds.size} numbers")
            self.bounds = self.bounds.reshape(2, 3)
            if not np.isfinite(self.bounds).all() or (self.bounds[1] <= self.bounds[0]).any():
                raise MeshingError(f"bounds must be finite world corners, min below max on every axis, got {self.bounds.tolist()}")
        arrays, _ = read_splats(obj)
        self.count = arrays.count
        bpy.context.view_layer.update()  # matrix_world is stale until the view layer updates
        self.matrix = object_matrix(obj)  # the object's frame -> world
        if cameras is not None:
            cameras = list(cameras)
            if not cameras:
                raise MeshingError(f"no cameras to render '{obj.name}' from (pass None for views around it)")
            cameras = _render_cameras(cameras, bpy.context.scene)
        self.cameras, self.views, self.surfels = [], [], None
        if self.method == "fusion":
            self._prepare_fusion(arrays, cameras)
        else:
            self.options = dict(resolution=self.resolution, padding=float(padding), trim=DEFAULT_TRIM if trim is None else float(trim))
            if camera_centres is None and cameras is not None:
                camera_centres = [camera.center for camera in cameras]
            centres = None
            if camera_centres is not None:  # world space -> the object's frame
                to_local = np.linalg.inv(self.matrix)
                centres = np.asarray(camera_centres, dtype=np.float64).reshape(-1, 3) @ to_local[:3, :3].T + to_local[:3, 3]
            self.surfels = GaussianModel.from_arrays(arrays).surfel_samples(float(min_opacity), int(max_points) if max_points else None, centres)
            if len(self.surfels[0]) == 0:
                raise MeshingError(f"no splat of '{obj.name}' has opacity >= {min_opacity:g} (of {self.count:,}); nothing to mesh")
        self.surface = self.mesh = None
        self.progress = (0, self.total)
        super().__init__()
        self.thread_name = f"mlx3d mesh {self.source_name}"

    def _prepare_fusion(self, arrays, cameras):
        from mlx3d.meshing.fusion import is_surfel_model, orbit_cameras

        if self.resolution < 8:
            raise MeshingError(f"resolution must be at least 8 voxels, got {self.resolution}")
        if not np.isfinite(self.matrix).all() or abs(np.linalg.det(self.matrix[:3, :3])) < 1e-12:
            raise MeshingError(f"'{self.source_name}' has a degenerate transform (a zero scale); nothing to mesh")
        if not (arrays.opacities >= np.log(_VISIBLE_OPACITY / (1.0 - _VISIBLE_OPACITY))).any():
            raise MeshingError(f"no splat of '{self.source_name}' is opaque enough to be rendered "
                               f"(opacity >= 1/255, of {self.count:,}); nothing to mesh")
        model = GaussianModel.from_arrays(arrays)
        self.model = model if np.array_equal(self.matrix, np.eye(4)) else model.transform(self.matrix)  # world space
        self.cameras = orbit_cameras(self.model) if cameras is None else cameras
        self.planar = is_surfel_model(self.model)

    # -- progress
    @property
    def total(self) -> int:
        """Progress steps of the whole extraction: fusion 3 per view; Poisson 1 until its solver reports its own."""
        return 3 * len(self.cameras) if self.method == "fusion" else 1

    @property
    def views_left(self) -> int:
        """Views still to render (``render_next``); always 0 for Poisson."""
        return len(self.cameras) - len(self.views)

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    def _check_cancel(self):
        if self._cancel.is_set():
            raise ExtractionCancelled(f"mesh extraction from '{self.source_name}' cancelled")

    def _report(self, progress, offset=None):
        """A ``progress(done, total)`` that raises ``ExtractionCancelled`` after ``cancel()``; fusion's
        reports are shifted by ``offset`` steps within ``total``."""
        def report(done, total):
            self._check_cancel()
            if offset is not None:
                done, total = offset + done, self.total
            self.progress = (done, total)
            if progress is not None:
                progress(done, total)
        return report

    # -- rendering (fusion; main thread)
    def render_next(self, progress=None) -> bool:
        """Render the depth and colour of the next view (MLX: call on the main thread); True while views remain."""
        if self.views_left == 0:
            return False
        self._check_cancel()
        self.views.append(self._render(self.cameras[len(self.views)]))
        self._report(progress, 0)(len(self.views), self.total)
        return self.views_left > 0

    def _render(self, camera):
        from mlx3d.meshing.fusion import depth_views

        return depth_views(self.model, [camera], planar=self.planar)[0]

    # -- meshing (any thread once the views are rendered)
    def _fuse(self, progress):
        from mlx3d.meshing import fuse_depth_maps
        from mlx3d.meshing.fusion import require_surface

        require_surface(self.views, what=f"the splats of '{self.source_name}'")
        surface = fuse_depth_maps(self.views, self.resolution, bounds=self.bounds, progress=self._report(progress, len(self.cameras)))
        to_local = np.linalg.inv(self.matrix)  # world -> the object's frame
        vertices = surface.vertices.astype(np.float64) @ to_local[:3, :3].T + to_local[:3, 3]
        return SurfaceMesh(vertices, surface.faces, surface.colors)

    def compute(self, progress=None):
        """The surface (an ``mlx3d.meshing.SurfaceMesh``, in the object's frame); raises ``MeshingError`` for bad input.
        Fusion renders the views left first, so call it on the main thread unless every view is rendered."""
        if self.method == "fusion":
            while self.views_left:
                self.render_next(progress)
            surface = self._fuse(progress)
        else:
            surface = reconstruct_surface(*self.surfels, progress=self._report(progress), **self.options)
        if self.cleanup:
            surface = keep_large_components(surface, self.cleanup)
        if self.faces:
            surface = simplify(surface, self.faces)
        self._check_cancel()  # a cancel that came after the last report still counts
        self.progress = (self.total, self.total) if self.method == "fusion" else (1, 1)
        self.surface = surface
        return surface

    def work(self):
        self._check_cancel()
        if self.views_left:
            raise RuntimeError(f"{self.views_left} of {len(self.cameras)} views of '{self.source_name}' are not rendered: "
                               "call render_next() on the main thread until none is left before start()")
        self.compute()

    def add_object(self):
        """The mesh object, parented to the splat object with an identity parent inverse; (object, messages)."""
        if self.error is not None:
            raise self.error
        if self.cancelled:
            raise ExtractionCancelled(f"mesh extraction from '{self.source_name}' cancelled")
        if self.surface is None:
            raise RuntimeError("add_object needs a finished computation (compute() or start() first)")
        try:
            self.source.name
        except ReferenceError:
            raise SplatObjectError(f"the splat object '{self.source_name}' was removed during the mesh extraction") from None
        vertices, faces, colors = _mesh_arrays(self.surface, self.source_name)
        self.mesh = SurfaceMesh(vertices, faces, colors)  # what the object holds
        collection = self.collection or (self.source.users_collection[0] if self.source.users_collection else bpy.context.collection)
        obj = new_mesh_object(self.name, vertices, faces, colors, collection=collection, parent=self.source)
        seconds = time.perf_counter() - self.t0
        how = f"fusion of {len(self.cameras)} views" if self.method == "fusion" else "Poisson"
        return obj, [
            f"extracted '{obj.name}' from '{self.source_name}' ({self.count:,} splats, {how}, resolution {self.resolution}): "
            f"{len(vertices):,} vertices, {len(faces):,} faces in {seconds:.1f} s"
        ]


def _mesh_arrays(surface, source_name):
    """Checked (vertices float32, faces int32, colours or None) of a SurfaceMesh; faces with a repeated corner are dropped."""
    vertices = np.ascontiguousarray(surface.vertices, dtype=np.float32).reshape(-1, 3)
    faces = np.ascontiguousarray(surface.faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise MeshingError(f"the mesh of '{source_name}' has faces indexing missing vertices")
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
    if len(faces) == 0:
        raise MeshingError(f"no surface found in '{source_name}' (try a lower opacity threshold or a higher resolution)")
    colors = None if surface.colors is None else np.asarray(surface.colors, dtype=np.float64).reshape(-1, 3)
    return vertices, faces.astype(np.int32), colors


def mesh_material():
    """The material of extracted meshes (reused when it exists): Principled BSDF coloured by the ``Color`` attribute."""

    def build(nodes, links):
        attr = nodes.new("ShaderNodeVertexColor")
        attr.layer_name = MESH_COLOR_ATTRIBUTE
        bsdf = nodes.new("ShaderNodeBsdfPrincipled")
        out = nodes.new("ShaderNodeOutputMaterial")
        links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
        links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        for i, node in enumerate((attr, bsdf, out)):
            node.location = (300 * i - 300, 0)

    return node_material(MESH_MATERIAL, build)


def new_mesh_object(name, vertices, faces, colors=None, *, collection, parent=None):
    """A mesh object from (V,3) vertices and (F,3) triangles, built with ``foreach_set``.

    colors: (V,3) sRGB-encoded values in [0, 1] (as training images hold them),
    stored linear in the FLOAT_COLOR point attribute ``Color`` that the ``MLX3D
    Mesh`` material shows. The object sits exactly under ``parent`` (identity
    parent inverse). Nothing is left behind if it fails.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    mesh = bpy.data.meshes.new(name)
    obj = None
    try:
        mesh.vertices.add(len(vertices))
        mesh.vertices.foreach_set("co", vertices.ravel())
        mesh.loops.add(faces.size)
        mesh.loops.foreach_set("vertex_index", faces.ravel())
        mesh.polygons.add(len(faces))
        mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
        mesh.update(calc_edges=True)
        if hasattr(mesh, "shade_smooth"):
            mesh.shade_smooth()
        else:  # before 4.1
            mesh.polygons.foreach_set("use_smooth", np.ones(len(faces), dtype=bool))
        if colors is not None:
            rgba = np.ones((len(vertices), 4), dtype=np.float32)
            rgba[:, :3] = srgb_to_linear(colors)
            attr = mesh.color_attributes.new(MESH_COLOR_ATTRIBUTE, "FLOAT_COLOR", "POINT")
            attr.data.foreach_set("color", rgba.ravel())
            mesh.color_attributes.active_color = attr
            if hasattr(mesh.color_attributes, "default_color_name"):
                mesh.color_attributes.default_color_name = attr.name
            mesh.materials.append(mesh_material())
        obj = bpy.data.objects.new(name, mesh)
        collection.objects.link(obj)
        if parent is not None:
            obj.parent = parent
            obj.matrix_parent_inverse.identity()
        obj.matrix_basis.identity()
    except BaseException:
        if obj is not None:
            bpy.data.objects.remove(obj, do_unlink=True)
        bpy.data.meshes.remove(mesh, do_unlink=True)
        raise
    return obj


def extract_mesh(obj, *, method="fusion", cameras=None, resolution=128, cleanup=0.01, faces=0, min_opacity=0.01, max_points=200000,
                 trim=None, name=None, collection=None, camera_centres=None, bounds=None, progress=None):
    """A triangle mesh of the splats' surface as a new mesh object under the splat object.

    method: ``'fusion'`` (default): depth and colour rendered from ``cameras``
    (Blender camera objects, each at the scene's output size, or
    ``mlx3d.cameras.Camera`` in world space; None: 60 views of 512 x 512 pixels
    around the splats, ``mlx3d.meshing.fusion.orbit_cameras``), fused into a
    truncated signed distance volume over the splats in world space (so any
    object transform is exact), and its zero level brought back to the
    object's frame; space no view saw is left empty. ``'poisson'``: the splats
    read in the object's frame as oriented discs and meshed by
    ``GaussianModel.surface_mesh`` (min_opacity: splats below it are left out;
    max_points: at most this many surfels, None or 0: all; trim: voxels, 0 =
    off, None = mlx3d's default; camera_centres: (C,3) world positions, by
    default the centres of ``cameras``: each splat's normal is turned to face
    the nearest; without them each splat keeps its own normal, the axis of its
    smallest scale). resolution: voxels along the longest side of the seen
    surface (fusion) or of the grid (Poisson). cleanup: pieces with fewer
    faces than this fraction of the largest piece's are dropped (0 keeps all).
    faces: at most this many triangles (``mlx3d.meshing.simplify``; 0: as
    extracted).
    bounds: fusion only, (2, 3) min and max world corners of the volume to
    mesh (``box_world_bounds`` of a box object), e.g. around an object on a
    floor; default: the surfaces the views share
    (``mlx3d.meshing.fusion.fusion_grid``).

    The object, named ``name`` (default "<splat object> mesh") and linked to
    ``collection`` (default the splat object's), is parented to the splat
    object with an identity parent inverse, so its world matrix is the splat
    object's; its vertex colours are the rendered colours (fusion) or the
    splats' base colour (Poisson). progress: ``progress(done, total)``, which
    may raise to cancel. Returns (object, messages). Bad input (not a splat
    object, no splats, none opaque enough, an object in ``cameras`` that is
    not a camera) raises a ``ValueError`` (``MeshingError``,
    ``SplatObjectError``) and adds nothing.
    """
    job = MeshExtraction(obj, method=method, cameras=cameras, resolution=resolution, cleanup=cleanup, faces=faces, min_opacity=min_opacity,
                         max_points=max_points, trim=trim, camera_centres=camera_centres, name=name, collection=collection,
                         bounds=bounds)
    job.compute(progress)
    return job.add_object()
