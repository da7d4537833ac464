"""Splat objects: Blender point clouds whose point attributes hold every 3DGS PLY property.

Attributes (POINT domain). The raw ones are the source of truth for export:

==============  ============  ==============================================
attribute       type          PLY properties
==============  ============  ==============================================
position        FLOAT_VECTOR  x y z (object space)
f_dc            FLOAT_VECTOR  f_dc_0..2
f_rest_<i>      FLOAT         f_rest_i (channel-major, as in the file)
opacity         FLOAT         opacity (logit)
log_scale       FLOAT_VECTOR  scale_0..2 (log standard deviations)
rot             QUATERNION    rot_0..3 (w,x,y,z as stored, not normalised)
<name>          FLOAT / INT   any other property (nx ny nz included); its PLY
                              type is kept in the data's ``mlx3d_ply_types``
==============  ============  ==============================================

Display attributes are derived from those and never exported: ``radius``,
``splat_color`` (linear RGB from f_dc, alpha = opacity) and ``rotation`` (the
unit quaternion) for the viewport, Cycles and the ellipsoid display; on
Blender 5.3+ also ``scale``, ``radiance:base`` and ``radiance:sh_<k>``,
completing the layout of Blender's own splat importer, so its native
renderer draws our objects. Point clouds made by that importer (without the raw
attributes) are read from those attributes instead.

Bulk data moves only through ``foreach_get``/``foreach_set`` on contiguous
float32/int32 arrays. This module imports ``bpy``; the math lives in ``mlx3d``.
"""

from __future__ import annotations

import json
import re

import bpy
import numpy as np
from mathutils import Matrix

from mlx3d.io import SplatArrays
from mlx3d.splatting import C0, transform_splats

RAW_ATTRIBUTES = ("f_dc", "opacity", "log_scale", "rot")
TYPES_KEY = "mlx3d_ply_types"
MATERIAL_NAME = "MLX3D Splat"
NATIVE_SPLAT_VERSION = (5, 3, 0)
_DISPLAY = {"radius", "splat_color", "rotation"}
_NATIVE = {"scale", "rotation", "radiance:base"}
_NATIVE_SH = re.compile(r"^radiance:sh_(\d+)$")
_F_REST = re.compile(r"^f_rest_(\d+)$")
# data_type -> (components, foreach key, numpy dtype)
_LAYOUT = {
    "FLOAT": (1, "value", np.float32),
    "INT": (1, "value", np.int32),
    "INT8": (1, "value", np.int8),
    "BOOLEAN": (1, "value", np.bool_),
    "FLOAT_VECTOR": (3, "vector", np.float32),
    "QUATERNION": (4, "value", np.float32),
    "FLOAT_COLOR": (4, "color", np.float32),
    "FLOAT4": (4, "vector", np.float32),  # Blender 5.3+ (radiance:base)
}
_INT_TYPES = {np.dtype(t) for t in (np.int8, np.uint8, np.int16, np.uint16, np.int32)}


class SplatObjectError(ValueError):
    """An object cannot be read as, or turned into, a splat object (the message says why)."""


# --------------------------------------------------------------------------- attributes
def _get(attributes, name: str, n: int, out: np.ndarray | None = None) -> np.ndarray:
    """Attribute values as (n,) or (n, components); ``out`` is a contiguous buffer to fill."""
    attr = attributes[name]
    comps, key, dtype = _LAYOUT[attr.data_type]
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
    comps, key, dtype = _LAYOUT[data_type]
    attr.data.foreach_set(key, np.ascontiguousarray(values, dtype=dtype).ravel())


def is_splat_object(obj) -> bool:
    """True for point cloud objects holding splats (ours, or Blender 5.3's native ones)."""
    if obj is None or obj.type != "POINTCLOUD":
        return False
    names = obj.data.attributes.keys()
    return all(a in names for a in RAW_ATTRIBUTES) or all(a in names for a in _NATIVE)


def splat_count(obj) -> int:
    return len(obj.data.points)


# --------------------------------------------------------------------------- reading
def read_splats(obj) -> tuple[SplatArrays, list[str]]:
    """The object's splats in object space, and warnings (attributes not exported)."""
    if not is_splat_object(obj):
        raise SplatObjectError(f"'{obj.name}' is not a splat object (a point cloud with f_dc, opacity, log_scale and rot attributes)")
    attributes = obj.data.attributes
    n = splat_count(obj)
    means = _get(attributes, "position", n)
    if all(a in attributes for a in RAW_ATTRIBUTES):
        arrays, used = _read_raw(attributes, n, means, obj.name)
    else:
        arrays, used = _read_native(attributes, n, means, obj.name)
    types = json.loads(obj.data.get(TYPES_KEY, "{}"))
    skipped = []
    order = [name for name in types if name in attributes] + [a.name for a in attributes if a.name not in types]
    for name in order:
        attr = attributes[name]
        if name in used or name == "position" or name.startswith(".") or name in _DISPLAY or name in _NATIVE or _NATIVE_SH.match(name):
            continue
        if attr.domain != "POINT" or _LAYOUT.get(attr.data_type, (0,))[0] != 1:
            skipped.append(f"{name} ({attr.data_type})")
            continue
        values = _get(attributes, name, n)
        ply_type = np.dtype(types.get(name, values.dtype.str))
        arrays.extra[name] = values.view(ply_type) if ply_type.itemsize == values.dtype.itemsize and ply_type.kind in "iu" else values.astype(ply_type)
    warnings = [f"'{obj.name}': attributes {', '.join(skipped)} are not PLY scalars and are not exported"] if skipped else []
    return arrays, warnings


def _read_raw(attributes, n, means, name):
    rest_ids = sorted(int(m.group(1)) for m in (_F_REST.match(a.name) for a in attributes) if m)
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
    return arrays, set(RAW_ATTRIBUTES) | {f"f_rest_{i}" for i in rest_ids}


def _read_native(attributes, n, means, name):
    """Raw 3DGS values from the attributes Blender 5.3's PLY importer writes."""
    sh_ids = sorted(int(m.group(1)) for m in (_NATIVE_SH.match(a.name) for a in attributes) if m)
    if sh_ids != list(range(len(sh_ids))) or len(sh_ids) not in (0, 3, 8, 15):
        raise SplatObjectError(f"'{name}': radiance:sh_* attributes must be numbered 0..2, 0..7 or 0..14, found {sh_ids}")
    base = _get(attributes, "radiance:base", n)
    alpha = np.clip(base[:, 3].astype(np.float64), 1e-7, 1 - 1e-7)
    scale = np.maximum(_get(attributes, "scale", n).astype(np.float64), 1e-30)
    rest = np.stack([_get(attributes, f"radiance:sh_{k}", n) for k in sh_ids], axis=1) if sh_ids else np.zeros((n, 0, 3), np.float32)
    arrays = SplatArrays(
        means=means,
        scales=np.log(scale).astype(np.float32),
        quats=_get(attributes, "rotation", n),
        opacities=np.log(alpha / (1 - alpha)).astype(np.float32),
        sh_dc=np.ascontiguousarray(base[:, None, :3]),
        sh_rest=rest,
    )
    return arrays, _NATIVE | {f"radiance:sh_{k}" for k in sh_ids}


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
def _ply_type_record(extra: dict) -> dict:
    return {name: values.dtype.str for name, values in extra.items()}


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


def _reserved(name: str) -> bool:
    return name in RAW_ATTRIBUTES or name == "position" or name in _DISPLAY or name in _NATIVE or bool(_F_REST.match(name) or _NATIVE_SH.match(name))


def new_pointcloud(name: str, arrays: SplatArrays) -> tuple["bpy.types.PointCloud", list[str]]:
    """A new point cloud data-block holding ``arrays`` (raw and display attributes), and warnings."""
    arrays.validate()
    clash = [k for k in arrays.extra if _reserved(k)]
    if clash:
        raise SplatObjectError(f"extra properties {clash} clash with splat attribute names")
    n = arrays.count
    mesh = bpy.data.meshes.new(name)
    carrier = bpy.data.objects.new(name, mesh)
    scene = bpy.context.scene
    scene.collection.objects.link(carrier)
    try:
        mesh.vertices.add(n)
        mesh.vertices.foreach_set("co", np.ascontiguousarray(arrays.means, np.float32).ravel())
        with bpy.context.temp_override(active_object=carrier, object=carrier, selected_objects=[carrier], selected_editable_objects=[carrier]):
            bpy.ops.object.convert(target="POINTCLOUD")
        if carrier.type != "POINTCLOUD":
            raise SplatObjectError(f"Blender did not convert '{name}' into a point cloud")
        cloud = carrier.data
    finally:
        scene.collection.objects.unlink(carrier)
        bpy.data.objects.remove(carrier)
        if mesh.users == 0:
            bpy.data.meshes.remove(mesh)
    warnings = write_attributes(cloud, arrays)
    return cloud, warnings


def write_attributes(cloud, arrays: SplatArrays) -> list[str]:
    """Fill ``cloud`` (n points) with the raw, extra and display attributes of ``arrays``."""
    attributes = cloud.attributes
    _set(attributes, "f_dc", "FLOAT_VECTOR", arrays.sh_dc[:, 0, :])
    rest = np.asarray(arrays.sh_rest, np.float32).transpose(0, 2, 1)  # (N, 3, K-1): channel-major
    k1 = rest.shape[2]
    for c in range(3):
        for k in range(k1):
            _set(attributes, f"f_rest_{c * k1 + k}", "FLOAT", rest[:, c, k])
    _set(attributes, "opacity", "FLOAT", arrays.opacities)
    _set(attributes, "log_scale", "FLOAT_VECTOR", arrays.scales)
    _set(attributes, "rot", "QUATERNION", arrays.quats)
    warnings = []
    for name, values in arrays.extra.items():
        data_type, stored, warning = _attribute_for(name, values)
        _set(attributes, name, data_type, stored)
        if warning:
            warnings.append(warning)
    cloud[TYPES_KEY] = json.dumps(_ply_type_record(arrays.extra))
    update_display(cloud, arrays)
    return warnings


def srgb_to_linear(c) -> np.ndarray:
    """Inverse sRGB transfer function (IEC 61966-2-1) of values clipped to [0, 1]."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def update_display(cloud, arrays: SplatArrays) -> None:
    """Write the derived display attributes (and Blender 5.3's native splat layout)."""
    scales = np.exp(arrays.scales.astype(np.float64))
    opacity = 1.0 / (1.0 + np.exp(-arrays.opacities.astype(np.float64)))
    # point radius: twice the geometric-mean standard deviation
    _set(cloud.attributes, "radius", "FLOAT", 2.0 * np.cbrt(np.prod(scales, axis=1)))
    rgb = np.clip(0.5 + C0 * arrays.sh_dc[:, 0, :].astype(np.float64), 0.0, 1.0)
    _set(cloud.attributes, "splat_color", "FLOAT_COLOR", np.column_stack([srgb_to_linear(rgb), opacity]))
    quats = arrays.quats.astype(np.float64)
    quats /= np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-30)
    _set(cloud.attributes, "rotation", "QUATERNION", quats)
    if bpy.app.version >= NATIVE_SPLAT_VERSION:
        _write_native(cloud, arrays, scales, opacity)
    _ensure_material(cloud)


def _write_native(cloud, arrays, scales, opacity) -> None:
    """Blender 5.3+: the attributes its own splat importer writes, so its renderer draws ours."""
    types = {item.identifier for item in bpy.types.Attribute.bl_rna.properties["data_type"].enum_items}
    float4 = "FLOAT4" if "FLOAT4" in types else "FLOAT_COLOR"
    _set(cloud.attributes, "scale", "FLOAT_VECTOR", scales)
    _set(cloud.attributes, "radiance:base", float4, np.column_stack([arrays.sh_dc[:, 0, :], opacity]))
    for k in range(arrays.sh_rest.shape[1]):
        _set(cloud.attributes, f"radiance:sh_{k}", "FLOAT_VECTOR", arrays.sh_rest[:, k, :])
    type_prop = cloud.bl_rna.properties.get("type")
    if type_prop is not None:
        splat_types = [item.identifier for item in type_prop.enum_items if "SPLAT" in item.identifier]
        if splat_types:
            cloud.type = splat_types[0]


def node_material(name: str, build):
    """The material ``name`` (reused when it exists), else a new one whose
    emptied node tree ``build(nodes, links)`` fills."""
    mat = bpy.data.materials.get(name)
    if mat is None:
        mat = bpy.data.materials.new(name)
        if bpy.app.version < (5, 0, 0):  # 5.0+ materials always use nodes
            mat.use_nodes = True
        mat.node_tree.nodes.clear()
        build(mat.node_tree.nodes, mat.node_tree.links)
    return mat


def attribute_material(name: str, attribute_type: str = "GEOMETRY", transparent: bool = True):
    """An emissive material coloured by ``splat_color`` (reused when it exists).

    attribute_type: where the shader reads the attribute ('GEOMETRY' for the
    points themselves, 'INSTANCER' for instances on them); transparent: mix
    with a transparent shader by the attribute's alpha (the splat opacity).
    """

    def build(nodes, links):
        attr = nodes.new("ShaderNodeAttribute")
        attr.attribute_type = attribute_type
        attr.attribute_name = "splat_color"
        emission = nodes.new("ShaderNodeEmission")
        out = nodes.new("ShaderNodeOutputMaterial")
        links.new(attr.outputs["Color"], emission.inputs["Color"])
        chain = [attr, emission]
        shader = emission.outputs["Emission"]
        if transparent:
            clear = nodes.new("ShaderNodeBsdfTransparent")
            mix = nodes.new("ShaderNodeMixShader")
            links.new(attr.outputs["Alpha"], mix.inputs["Fac"])
            links.new(clear.outputs["BSDF"], mix.inputs[1])
            links.new(shader, mix.inputs[2])
            chain += [clear, mix]
            shader = mix.outputs["Shader"]
        links.new(shader, out.inputs["Surface"])
        for i, node in enumerate(chain + [out]):
            node.location = (220 * i - 440, 0)

    return node_material(name, build)


def _ensure_material(cloud) -> None:
    mat = attribute_material(MATERIAL_NAME)
    if mat.name not in cloud.materials:
        cloud.materials.append(mat)


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
    return obj, warnings


def replace_splats(obj, arrays: SplatArrays) -> list[str]:
    """Swap the object's point cloud for one holding ``arrays`` (counts may differ)."""
    old = obj.data
    cloud, warnings = new_pointcloud(old.name, arrays)
    obj.data = cloud
    if old.users == 0:
        bpy.data.pointclouds.remove(old)
    return warnings
