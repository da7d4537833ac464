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
import warnings
from contextlib import contextmanager

import bpy
import numpy as np

from mlx3d.floaters import radius_outliers, statistical_outliers
from mlx3d.io import read_splat_ply, write_splat_ply
from mlx3d.splatting import GaussianModel, merge_splats

from .camera import camera_from_blender
from .splat_object import (
    SplatObjectError,
    baked_splats,
    create_splat_object,
    is_identity,
    is_splat_object,
    object_matrix,
    read_splats,
    replace_splats,
)

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
    """The splat objects among ``objects``, in the given order."""
    return [obj for obj in objects if is_splat_object(obj)]


def import_splat_file(path, *, sh_degree=None, drop_nonfinite=False, axis="NONE", location=None, collection=None):
    """Import one 3DGS PLY file as a splat object named after it.

    sh_degree: cap (truncate/pad) or None for the file's degree; drop_nonfinite:
    drop rows with NaN/Inf (counted in the messages) instead of refusing the
    file; axis: an ``AXIS_PRESETS`` key applied as the object's transform;
    location: world position of the object origin (e.g. the 3D cursor).
    Returns (object, messages). A bad file raises ``PlyFormatError`` and
    leaves the scene untouched.
    """
    matrix = axis_matrix(axis).copy()
    notes: list = []
    with _warnings_into(notes):
        arrays = read_splat_ply(path, sh_degree=sh_degree, nonfinite="drop" if drop_nonfinite else "error")
    if location is not None:
        matrix[:3, 3] = np.asarray(location, dtype=np.float64)
    name = os.path.splitext(os.path.basename(os.fspath(path)))[0]
    obj, messages = create_splat_object(name, arrays, collection=collection, matrix=None if is_identity(matrix) else matrix)
    return obj, [f"imported {arrays.count:,} splats (SH degree {arrays.sh_degree}) from {os.path.basename(os.fspath(path))}"] + notes + messages


def export_splat_file(path, objects, *, axis="NONE", sh_degree=None):
    """Write the splat objects, each with its world transform baked in, into one PLY file.

    axis: the inverse of an ``AXIS_PRESETS`` key is applied (so a file imported
    with a preset exports back to its own axes). Returns (count, messages).
    """
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
    write_splat_ply(path, merged)
    names = ", ".join(obj.name for obj in objects)
    return merged.count, [f"exported {merged.count:,} splats from {names} to {os.path.basename(os.fspath(path))}"] + messages


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


def crop_to_box(obj, box, *, keep_inside=True):
    """Keep (or delete) the splats inside the bounds of ``box`` (a mesh's bounding box or an empty's cube)."""
    if box is None or box == obj:
        raise SplatObjectError("choose a mesh or empty (other than the splat object) as the crop box")
    if box.type == "EMPTY":
        size = box.empty_display_size
        lo, hi = np.full(3, -size), np.full(3, size)
    elif box.type == "MESH":
        corners = np.array([list(c) for c in box.bound_box], dtype=np.float64)
        lo, hi = corners.min(axis=0), corners.max(axis=0)
    else:
        raise SplatObjectError(f"crop box '{box.name}' must be a mesh or an empty, not {box.type}")
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


RENDER_IMAGE = "MLX3D Render"


def render_splats(objects, scene, *, camera_object=None, antialias=False, background=(0.0, 0.0, 0.0), filepath=None, backend="auto"):
    """Render splat objects (world transforms baked) from the scene camera with mlx3d.

    The result goes into the Blender image ``RENDER_IMAGE`` (sRGB, the size of
    the scene's render resolution) and, when ``filepath`` is given, a PNG
    written atomically. Returns (image, messages).
    """
    objects = splat_objects(objects)
    if not objects:
        raise SplatObjectError("no splat objects to render")
    camera_object = camera_object or scene.camera
    if camera_object is None or camera_object.type != "CAMERA":
        raise SplatObjectError("the scene has no active camera to render from")
    cam = camera_from_blender(camera_object, scene)
    bpy.context.view_layer.update()
    messages: list = []
    parts = []
    for obj in objects:
        arrays, warnings_ = baked_splats(obj)
        parts.append(arrays)
        messages += warnings_
    with _warnings_into(messages):
        arrays = parts[0] if len(parts) == 1 else merge_splats(parts)
    out = GaussianModel.from_arrays(arrays).render(cam, background=tuple(background), antialias=antialias, backend=backend)
    rgb = np.clip(np.array(out["image"], dtype=np.float32), 0.0, 1.0)
    rgba = np.concatenate([rgb, np.ones(rgb.shape[:2] + (1,), np.float32)], axis=-1)[::-1]  # Blender rows go bottom-up
    image = bpy.data.images.get(RENDER_IMAGE)
    if image is None or tuple(image.size) != (cam.width, cam.height):
        if image is not None:
            bpy.data.images.remove(image)
        image = bpy.data.images.new(RENDER_IMAGE, cam.width, cam.height, alpha=True)
    image.pixels.foreach_set(np.ascontiguousarray(rgba).ravel())
    image.update()
    names = ", ".join(o.name for o in objects)
    messages.insert(0, f"rendered {arrays.count:,} splats from {names} through '{camera_object.name}' at {cam.width}x{cam.height} ({', '.join(out['stages'])})")
    if filepath:
        _save_png(image, os.fspath(filepath))
        messages.append(f"saved {filepath}")
    return image, messages


def _save_png(image, path: str) -> None:
    """Save a Blender image as PNG via a temporary file and rename (no partial file on failure)."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise SplatObjectError(f"folder {folder} does not exist")
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{os.getpid()}.tmp.png")
    try:
        image.filepath_raw = tmp
        image.file_format = "PNG"
        image.save()
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
        image.filepath_raw = path
