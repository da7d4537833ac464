"""Splat objects: Blender point clouds in Blender's own Gaussian-splat layout.

The layout, and what each Blender version gets, is in ``splat_layout``. This
module reads any splat point cloud into ``SplatArrays`` (Blender's importer's,
ours, one made or edited by Geometry Nodes, or this add-on's earlier layout)
and writes ``SplatArrays`` into one. Bulk data moves only through
``foreach_get``/``foreach_set`` on contiguous float32/int32 arrays. This module
imports ``bpy``; the math lives in ``mlx3d``.
"""

from __future__ import annotations

import json

import bpy
import numpy as np
from mathutils import Matrix

from mlx3d.io import SplatArrays
from mlx3d.splatting import transform_splats

from . import display
from . import splat_layout as L

# data_type -> (components, foreach key, numpy dtype)
_TYPES = {
    "FLOAT": (1, "value", np.float32),
    "INT": (1, "value", np.int32),
    "INT8": (1, "value", np.int8),
    "BOOLEAN": (1, "value", np.bool_),
    "FLOAT_VECTOR": (3, "vector", np.float32),
    "QUATERNION": (4, "value", np.float32),
    "FLOAT_COLOR": (4, "color", np.float32),
    "FLOAT4": (4, "vector", np.float32),
}
_INT_TYPES = {np.dtype(t) for t in (np.int8, np.uint8, np.int16, np.uint16, np.int32)}
# the native attributes' accepted data types (radiance:base: FLOAT4, or FLOAT_COLOR where FLOAT4 is missing)
_EXPECTED = {L.BASE: ("FLOAT4", "FLOAT_COLOR"), L.SCALE: ("FLOAT_VECTOR",), L.ROTATION: ("QUATERNION",)}
# an alpha of 0 or 1 has no logit: alphas are clipped to [smallest normal float32, largest float32 below 1]
# (logits -87.3 to 16.6)
_ALPHA_RANGE = (float(np.finfo(np.float32).tiny), 1.0 - float(np.finfo(np.float32).epsneg))


class SplatObjectError(ValueError):
    """An object cannot be read as, or turned into, a splat object (the message says why)."""


# --------------------------------------------------------------------------- attributes
def _get(attributes, name: str, n: int, out: np.ndarray | None = None) -> np.ndarray:
    """Attribute values as (n,) or (n, components); ``out`` is a contiguous buffer to fill."""
    attr = attributes[name]
    comps, key, dtype = _TYPES[attr.data_type]
    if out is None:
        out = np.empty(n * comps, dtype=dtype)
    attr.data.foreach_get(key, out.reshape(-1))
    return out.reshape(n, comps) if comps > 1 else out


def _set(attributes, name: str, data_type: str, values: np.ndarray) -> None:
    attr = attributes.get(name)
    if attr is not None and (attr.data_type != data_type or attr.domain != "POINT"):
        attributes.remove(attr)
        attr = None
    if attr is None:
        attr = attributes.new(name, data_type, "POINT")
    comps, key, dtype = _TYPES[data_type]
    attr.data.foreach_set(key, np.ascontiguousarray(values, dtype=dtype).ravel())


def _remove(attributes, names) -> None:
    for name in list(names):
        attr = attributes.get(name)
        if attr is not None:
            attributes.remove(attr)


def _layout_of(attributes) -> str | None:
    """'legacy' (this add-on's earlier raw layout, whose raw attributes are the truth even where it
    also wrote Blender's as a display), 'native' or None."""
    if all(a in attributes for a in L.LEGACY_RAW):
        return "legacy"
    if all(a in attributes for a in L.NATIVE):
        return "native"
    return None


def _has_modifiers(obj) -> bool:
    """Whether the object has modifiers (other than the display) that may change what it holds."""
    return any(m.show_viewport and not display.is_display(m) for m in obj.modifiers)


def _evaluated_cloud(obj):
    """The point cloud Blender shows for ``obj``: its data-block, or with modifiers the
    evaluated geometry (the add-on's own display modifier left out)."""
    if not _has_modifiers(obj):
        return obj.data
    ours = [m for m in obj.modifiers if display.is_display(m) and m.show_viewport]
    for m in ours:
        m.show_viewport = False
    try:
        depsgraph = bpy.context.evaluated_depsgraph_get()
        depsgraph.update()
        return obj.evaluated_get(depsgraph).data
    finally:
        for m in ours:
            m.show_viewport = True


def is_splat_object(obj) -> bool:
    """True for point cloud objects holding splats: Blender's own Gaussian splats (from its
    importer, ours, or Geometry Nodes) or the add-on's earlier layout."""
    if obj is None or obj.type != "POINTCLOUD":
        return False
    if _layout_of(obj.data.attributes):
        return True
    if _has_modifiers(obj):
        evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        return evaluated.type == "POINTCLOUD" and _layout_of(evaluated.data.attributes) is not None
    return False


def has_splat_attributes(obj) -> bool:
    """Whether a point cloud carries any of the splat attributes (complete or not)."""
    return obj is not None and obj.type == "POINTCLOUD" and any(a in obj.data.attributes for a in L.NATIVE + L.LEGACY_RAW)


def splat_count(obj) -> int:
    return len(obj.data.points)


# --------------------------------------------------------------------------- reading
def read_splats(obj) -> tuple[SplatArrays, list[str]]:
    """The splats Blender shows for ``obj`` (modifiers applied), in object space, and warnings
    (attributes not exported). Raises ``SplatObjectError`` naming the object and attribute
    when one is missing or malformed."""
    if obj is None or obj.type != "POINTCLOUD":
        raise SplatObjectError(f"'{getattr(obj, 'name', obj)}' is not a point cloud, so it holds no splats")
    cloud = _evaluated_cloud(obj)
    attributes = cloud.attributes
    layout = _layout_of(attributes)
    if layout is None:
        present = [a for a in L.NATIVE if a in attributes]
        missing = [a for a in L.NATIVE if a not in attributes]
        what = f"it lacks {', '.join(missing)}" if present else "it has none of its attributes"
        raise SplatObjectError(f"'{obj.name}' is not a Gaussian-splat point cloud ({', '.join(L.NATIVE)}, radiance:sh_*): {what}")
    n = len(cloud.points)
    means = _get(attributes, "position", n)
    arrays, used = (_read_native if layout == "native" else _read_legacy)(attributes, n, means, obj.name)
    for field in ("means", "sh_dc", "sh_rest"):
        if not np.isfinite(getattr(arrays, field)).all():
            raise SplatObjectError(f"'{obj.name}': {_attribute_of(field, layout)} has NaN or infinite values; nothing was written")
    warnings = _read_extras(cloud, attributes, n, used, arrays)
    return arrays, [f"'{obj.name}': {w}" for w in warnings]


def _attribute_of(field: str, layout: str) -> str:
    if field == "means":
        return "position"
    if layout == "native":
        return {"sh_dc": L.BASE, "sh_rest": "radiance:sh_*"}[field]
    return {"sh_dc": "f_dc", "sh_rest": "f_rest_*"}[field]


def _check_type(attributes, name: str, obj_name: str) -> None:
    attr = attributes[name]
    allowed = _EXPECTED.get(name, ("FLOAT_VECTOR",))
    if attr.domain != "POINT" or attr.data_type not in allowed:
        raise SplatObjectError(
            f"'{obj_name}': attribute '{name}' is {attr.data_type} on {attr.domain}; "
            f"a splat needs {' or '.join(allowed)} on POINT")


def _raw_where_consistent(attributes, name: str, n: int, native: np.ndarray, derive) -> np.ndarray | None:
    """The hidden raw values of ``name`` (n, k) for the points whose native value still equals
    ``derive(raw)`` bit for bit, else None; a point whose native value changed keeps NaN."""
    attr = attributes.get(name)
    if attr is None or attr.domain != "POINT" or attr.data_type not in _TYPES:
        return None
    raw = _get(attributes, name, n).reshape(n, -1)
    if raw.shape[1] != native.reshape(n, -1).shape[1]:
        return None
    same = (derive(raw).reshape(n, -1) == native.reshape(n, -1)).all(axis=1)
    return np.where(same[:, None], raw, np.nan)


def _sigmoid32(logits: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-logits.astype(np.float64)))).astype(np.float32)


def _exp32(log_scales: np.ndarray) -> np.ndarray:
    return np.exp(log_scales.astype(np.float64)).astype(np.float32)


def _normalised32(quats: np.ndarray) -> np.ndarray:
    q = quats.astype(np.float64)
    return (q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)).astype(np.float32)


def _fill(raw: np.ndarray | None, derived: np.ndarray) -> np.ndarray:
    """Raw values where they are kept (not NaN), ``derived`` elsewhere."""
    if raw is None:
        return derived
    raw = raw.reshape(derived.shape)
    return np.where(np.isnan(raw), derived, raw).astype(np.float32)


def _read_native(attributes, n, means, name):
    """Raw 3DGS values from Blender's splat attributes (and the hidden raw values kept beside them)."""
    for a in L.NATIVE:
        _check_type(attributes, a, name)
    sh_ids = sorted(int(m.group(1)) for m in (L.SH_PATTERN.match(a.name) for a in attributes) if m)
    if sh_ids != list(range(len(sh_ids))) or len(sh_ids) not in (0, 3, 8, 15):
        raise SplatObjectError(f"'{name}': radiance:sh_* attributes must be numbered 0..2, 0..7 or 0..14, found {sh_ids}")
    for k in sh_ids:
        _check_type(attributes, f"radiance:sh_{k}", name)
    base = _get(attributes, L.BASE, n)
    alpha = base[:, 3]
    scale = _get(attributes, L.SCALE, n)
    rotation = _get(attributes, L.ROTATION, n)
    if not np.isfinite(alpha).all() or ((alpha < 0) | (alpha > 1)).any():
        raise SplatObjectError(f"'{name}': the alpha of {L.BASE} must lie in [0, 1] (it is sigmoid(opacity)); {int((~((alpha >= 0) & (alpha <= 1))).sum())} splats are outside or NaN")
    if not np.isfinite(scale).all() or (scale <= 0).any():
        raise SplatObjectError(f"'{name}': {L.SCALE} must be positive and finite (standard deviations); {int((~(scale > 0) | ~np.isfinite(scale)).any(axis=1).sum())} splats are not")
    norms = np.linalg.norm(rotation.astype(np.float64), axis=1)
    if not np.isfinite(norms).all() or (norms == 0).any():
        raise SplatObjectError(f"'{name}': {L.ROTATION} has {int((~(norms > 0) | ~np.isfinite(norms)).sum())} zero or non-finite quaternions")
    clipped = np.clip(alpha.astype(np.float64), *_ALPHA_RANGE)
    logits = np.log(clipped / (1.0 - clipped)).astype(np.float32)
    rest = np.stack([_get(attributes, f"radiance:sh_{k}", n) for k in sh_ids], axis=1) if sh_ids else np.zeros((n, 0, 3), np.float32)
    arrays = SplatArrays(
        means=means,
        scales=_fill(_raw_where_consistent(attributes, L.RAW_LOG_SCALE, n, scale, _exp32), np.log(scale.astype(np.float64)).astype(np.float32)),
        quats=_fill(_raw_where_consistent(attributes, L.RAW_ROT, n, rotation, _normalised32), rotation),
        opacities=_fill(_raw_where_consistent(attributes, L.RAW_OPACITY, n, alpha, _sigmoid32), logits),
        sh_dc=np.ascontiguousarray(base[:, None, :3]),
        sh_rest=rest,
    )
    return arrays, set(L.NATIVE) | {f"radiance:sh_{k}" for k in sh_ids}


def _read_legacy(attributes, n, means, name):
    """Raw 3DGS values from the add-on's earlier layout (f_dc, f_rest_*, opacity, log_scale, rot)."""
    rest_ids = sorted(int(m.group(1)) for m in (L.LEGACY_REST.match(a.name) for a in attributes) if m)
    if rest_ids != list(range(len(rest_ids))) or len(rest_ids) not in (0, 9, 24, 45):
        raise SplatObjectError(f"'{name}': f_rest attributes must be f_rest_0..f_rest_{{8, 23 or 44}}, found {len(rest_ids)} ({rest_ids[:3]}...)")
    k1 = len(rest_ids) // 3
    rest = np.empty((3 * k1, n), np.float32)  # one row per f_rest_i: channel-major like the file
    for i in rest_ids:
        _get(attributes, f"f_rest_{i}", n, out=rest[i])
    arrays = SplatArrays(
        means=means,
        scales=_get(attributes, "log_scale", n),
        quats=_get(attributes, "rot", n),
        opacities=_get(attributes, "opacity", n),
        sh_dc=_get(attributes, "f_dc", n)[:, None, :],
        sh_rest=np.ascontiguousarray(rest.reshape(3, k1, n).transpose(2, 1, 0)),
    )
    used = set(L.LEGACY_RAW) | {f"f_rest_{i}" for i in rest_ids} | set(L.LEGACY_DISPLAY) | set(L.NATIVE)
    return arrays, used | {a.name for a in attributes if L.SH_PATTERN.match(a.name)}


def _read_extras(cloud, attributes, n, used, arrays) -> list[str]:
    """Fill ``arrays.extra`` with the other PLY scalars (recorded order first); warnings."""
    types = json.loads(cloud.get(L.TYPES_KEY, "{}"))
    zeros = json.loads(cloud.get(L.ZERO_KEY, "[]"))
    skipped = []
    order = [name for name in types if name in attributes or name in zeros] + [a.name for a in attributes if a.name not in types]
    for name in order:
        if name in used or L.reserved(name):
            continue
        if name not in attributes:  # a property that was zero for every splat
            arrays.extra[name] = np.zeros(n, np.dtype(types[name]))
            continue
        attr = attributes[name]
        if attr.domain != "POINT" or _TYPES.get(attr.data_type, (0,))[0] != 1:
            skipped.append(f"{name} ({attr.data_type})")
            continue
        values = _get(attributes, name, n)
        ply_type = np.dtype(types.get(name, values.dtype.str))
        arrays.extra[name] = values.view(ply_type) if ply_type.itemsize == values.dtype.itemsize and ply_type.kind in "iu" else values.astype(ply_type)
    return [f"attributes {', '.join(skipped)} are not PLY scalars and are not exported"] if skipped else []


def object_matrix(obj, which: str = "world") -> np.ndarray:
    """4x4 float64 numpy copy of the object's ``matrix_world`` or ``matrix_basis``."""
    return np.array(obj.matrix_world if which == "world" else obj.matrix_basis, dtype=np.float64)


def is_identity(matrix: np.ndarray) -> bool:
    """Float32-level identity test: such matrices are skipped so untouched splats stay bit-exact."""
    return bool(np.allclose(matrix, np.eye(4), rtol=0.0, atol=1e-6))


def baked_splats(obj, matrix: np.ndarray | None = None) -> tuple[SplatArrays, list[str]]:
    """The object's splats with ``matrix`` (default: its world matrix) baked in."""
    arrays, warnings = read_splats(obj)
    matrix = object_matrix(obj) if matrix is None else matrix
    if not is_identity(matrix):
        arrays = transform_splats(arrays, matrix)
    return arrays, warnings


# --------------------------------------------------------------------------- writing
def _attribute_for(name: str, values: np.ndarray) -> tuple[str, np.ndarray, str | None]:
    """(data_type, values to store, warning) for an extra PLY property."""
    if values.dtype == np.float32:
        return "FLOAT", values, None
    if values.dtype in _INT_TYPES:
        return "INT", values.astype(np.int32), None
    if values.dtype == np.uint32:
        return "INT", values.view(np.int32), None  # bit pattern kept, type restored on export
    if values.dtype == np.float64:
        return "FLOAT", values.astype(np.float32), f"property '{name}' is float64 and is kept at float32 precision"
    raise SplatObjectError(f"property '{name}' has unsupported type {values.dtype}")


def pointcloud_from_positions(name: str, positions) -> "bpy.types.PointCloud":
    """A new point cloud data-block with these (N, 3) positions and no other attribute.

    Made from a mesh with Blender's own conversion, as every splat object is,
    so it behaves the same on every supported version; nothing else is left
    behind."""
    positions = np.ascontiguousarray(positions, np.float32).reshape(-1, 3)
    mesh = bpy.data.meshes.new(name)
    carrier = bpy.data.objects.new(name, mesh)
    scene = bpy.context.scene
    scene.collection.objects.link(carrier)
    try:
        mesh.vertices.add(len(positions))
        mesh.vertices.foreach_set("co", positions.ravel())
        with bpy.context.temp_override(active_object=carrier, object=carrier, selected_objects=[carrier], selected_editable_objects=[carrier]):
            bpy.ops.object.convert(target="POINTCLOUD")
        if carrier.type != "POINTCLOUD":
            raise SplatObjectError(f"Blender did not convert '{name}' into a point cloud")
        cloud = carrier.data
        _remove(cloud.attributes, [a.name for a in cloud.attributes if a.name.startswith(".")])  # the mesh's selection
    finally:
        scene.collection.objects.unlink(carrier)
        bpy.data.objects.remove(carrier)
        if mesh.users == 0:
            bpy.data.meshes.remove(mesh)
    return cloud


def new_pointcloud(name: str, arrays: SplatArrays) -> tuple["bpy.types.PointCloud", list[str]]:
    """A new point cloud data-block holding ``arrays`` in the splat layout, and warnings."""
    arrays.validate()
    clash = [k for k in arrays.extra if L.reserved(k) or k in L.LEGACY_RAW or L.LEGACY_REST.match(k)]
    if clash:
        raise SplatObjectError(f"extra properties {clash} clash with splat attribute names")
    cloud = pointcloud_from_positions(name, arrays.means)
    try:
        warnings = write_attributes(cloud, arrays)
    except Exception:
        bpy.data.pointclouds.remove(cloud)
        raise
    return cloud, warnings


def write_attributes(cloud, arrays: SplatArrays) -> list[str]:
    """Fill ``cloud`` (n points at ``arrays.means``) with the splat layout of the running Blender."""
    layout = L.current()
    attributes = cloud.attributes
    opacity, log_scales, quats = (np.asarray(a, np.float32) for a in (arrays.opacities, arrays.scales, arrays.quats))
    _set(attributes, L.BASE, layout.base_type, np.column_stack([arrays.sh_dc[:, 0, :], _sigmoid32(opacity)]))
    _set(attributes, L.SCALE, "FLOAT_VECTOR", _exp32(log_scales))
    _set(attributes, L.ROTATION, "QUATERNION", _normalised32(quats))
    for k in range(arrays.sh_rest.shape[1]):
        _set(attributes, f"radiance:sh_{k}", "FLOAT_VECTOR", arrays.sh_rest[:, k, :])
    _remove(attributes, [a.name for a in attributes if (m := L.SH_PATTERN.match(a.name)) and int(m.group(1)) >= arrays.sh_rest.shape[1]])
    _set(attributes, L.RAW_OPACITY, "FLOAT", opacity)
    _set(attributes, L.RAW_LOG_SCALE, "FLOAT_VECTOR", log_scales)
    _set(attributes, L.RAW_ROT, "QUATERNION", quats)
    warnings, zeros = [], []
    for name, values in arrays.extra.items():
        if arrays.count and not np.any(values):
            zeros.append(name)
            _remove(attributes, [name])
            continue
        data_type, stored, warning = _attribute_for(name, values)
        _set(attributes, name, data_type, stored)
        if warning:
            warnings.append(warning)
    cloud[L.TYPES_KEY] = json.dumps({name: values.dtype.str for name, values in arrays.extra.items()})
    cloud[L.ZERO_KEY] = json.dumps(zeros)
    if layout.splat_type:
        cloud.type = layout.splat_type
    return warnings


def upgrade(obj) -> bool:
    """Bring a splat object saved by another Blender or an earlier add-on version to the running
    Blender's layout (``splat_layout``); True if anything changed. Objects whose splats come from
    modifiers only are left as they are."""
    if obj is None or obj.type != "POINTCLOUD":
        return False
    cloud, layout = obj.data, L.current()
    attributes = cloud.attributes
    found = _layout_of(attributes)
    changed = False
    if found == "legacy":
        ellipsoids = display.remove_legacy(obj)
        if _has_modifiers(obj):
            return ellipsoids
        arrays, _ = read_splats(obj)
        write_attributes(cloud, arrays)
        legacy = set(L.LEGACY_RAW) | set(L.LEGACY_DISPLAY) | {a.name for a in attributes if L.LEGACY_REST.match(a.name)}
        _remove(attributes, legacy)
        for i in reversed(range(len(cloud.materials))):
            if cloud.materials[i] is not None and cloud.materials[i].name == L.LEGACY_MATERIAL:
                cloud.materials.pop(index=i)
        display.ensure(obj, layout.own_display, ellipsoids=ellipsoids or None)
        return True
    if found != "native":
        return False
    base = attributes[L.BASE]
    if base.data_type != layout.base_type and base.data_type in ("FLOAT4", "FLOAT_COLOR"):
        _set(attributes, L.BASE, layout.base_type, _get(attributes, L.BASE, len(cloud.points)))
        changed = True
    if layout.splat_type and getattr(cloud, "type", layout.splat_type) != layout.splat_type:
        cloud.type = layout.splat_type
        changed = True
    return display.ensure(obj, layout.own_display) or changed


def create_splat_object(name: str, arrays: SplatArrays, collection=None, matrix=None):
    """A new splat object holding ``arrays``, linked to ``collection`` (default: the active one).

    Returns (object, warnings). Nothing is left behind if it fails."""
    cloud, warnings = new_pointcloud(name, arrays)
    try:
        obj = bpy.data.objects.new(name, cloud)
    except Exception:
        bpy.data.pointclouds.remove(cloud)
        raise
    (collection or bpy.context.collection).objects.link(obj)
    if matrix is not None:
        obj.matrix_world = Matrix(np.asarray(matrix).tolist())
    display.ensure(obj, L.current().own_display)
    return obj, warnings


def replace_splats(obj, arrays: SplatArrays) -> list[str]:
    """Swap the object's point cloud for one holding ``arrays`` (counts may differ)."""
    old = obj.data
    cloud, warnings = new_pointcloud(old.name, arrays)
    obj.data = cloud
    if old.users == 0:
        bpy.data.pointclouds.remove(old)
    display.ensure(obj, L.current().own_display)
    return warnings


def srgb_to_linear(c) -> np.ndarray:
    """Inverse sRGB transfer function (IEC 61966-2-1) of values clipped to [0, 1]."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
