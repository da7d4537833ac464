"""glTF 2.0 splats: ``KHR_gaussian_splatting`` in ``.glb`` and ``.gltf`` (numpy only).

A splat primitive is a mesh primitive with ``mode`` 0 (POINTS) whose
``extensions`` hold ``KHR_gaussian_splatting`` (the Khronos extension, as
ratified: scale linear, opacity in [0, 1]).  Its attributes, one accessor
each, ``N`` elements::

    POSITION                                    VEC3    float: x, y, z
    KHR_gaussian_splatting:ROTATION             VEC4    unit quaternion x, y, z, w
    KHR_gaussian_splatting:SCALE                VEC3    linear standard deviations exp(scale_i)
    KHR_gaussian_splatting:OPACITY              SCALAR  alpha = sigmoid(opacity)
    KHR_gaussian_splatting:SH_DEGREE_0_COEF_0   VEC3    f_dc (r, g, b), raw
    KHR_gaussian_splatting:SH_DEGREE_l_COEF_n   VEC3    SH degree l = 1..3, n = 0..2l
                                                        (order m = n - l), raw; all of
                                                        a degree and the ones below
    COLOR_0                                     VEC4    fallback point colour (written,
                                                        ignored on read)
    _<name>                                     SCALAR  an extra property (float32,
                                                        int8/16, uint8/16[/32])

``.glb`` is the binary container: a 12-byte header (``glTF``, version 2, total
length), a JSON chunk (padded with spaces to 4 bytes), a BIN chunk holding
buffer 0.  ``.gltf`` is the JSON alone; its buffers are ``data:`` URIs
(base64) or files next to it.

Reading: every splat primitive instanced by a node of the default scene
(``scene``, else scene 0; without scenes the root nodes; without nodes the
meshes as they are), concatenated in scene order (SH padded with zeros to the
highest degree; only the extras every primitive has).  Accessors may be
interleaved (``byteStride``), offset, sparse, or without a buffer view
(zeros); besides float the extension's integer types are decoded: ROTATION
normalised int8/int16, SCALE uint8/uint16 (normalised or not), OPACITY
normalised uint8/uint16, and POSITION any integer type where
``KHR_mesh_quantization`` is used.  A file requiring another extension (a
compression) is refused, naming it.  A SCALE with negative values follows
the pre-ratification draft, which stored log scales: it is read as such,
with a warning.

Frames: glTF is right-handed, +Y up, +Z forward (the front faces +Z), so
+X is left ("LUF"); a 3DGS PLY is +X right, +Y down, +Z forward.  As
splat-transform does, a file is the PLY turned half a turn about Z:
``(x, y, z)_glTF = (-x, -y, z)_PLY``, quaternions multiplied on the left by
``(w, x, y, z) = (0, 0, 0, 1)``, SH coefficients of odd order ``m`` negated
(all exact in float32); no node transform is written.  Reading applies the
node's global transform ``M`` (matrix or TRS, with its parents') and then that
half turn: positions ``P M p`` (``P = diag(-1, -1, 1)``); rotations and SH by
the rotation of ``P M``; a uniform node scale multiplies the scales; a
non-uniform one is applied to each covariance (``P M C C^T M^T P``, refactored
into scale and rotation).  A mirroring node (determinant <= 0) is refused:
the extension leaves it undefined.  With no node transform the file's values
come back exactly (but for the activations below).

Bounds (float32 storage; through our writer and reader):

- positions, ``f_dc``, ``sh_rest``: exact;
- rotation: the quaternion is normalised (``w >= 0``) before the exact frame
  change; the rotation matrix within 1e-6;
- log scales ``s``: stored as float32 ``exp(s)``, read back as ``log``: within
  ``6e-8 + ulp(s) / 2`` for ``s`` in [-87, 88] (float32's normal range of
  ``exp``); a zero scale reads as ``log(2^-149) = -103.28``;
- opacity: alpha within float32 rounding (``6e-8``); the logit ``l`` within
  ``6e-8 * (1 + e^l) + ulp(l) / 2``, and logits above 16.6 (alpha rounds to
  1) read as 16.6;
- extras of dtype float32, int8, uint8, int16, uint16: exact; int32, uint32
  and float64 have no glTF attribute type and are not written (a warning
  names them).  PLY comments are not kept.
"""

from __future__ import annotations

import base64
import binascii
import json
import os
import re
import struct
import urllib.parse
import warnings

import numpy as np

from .. import __version__
from ..errors import SplatFormatError
from ..sh_basis import rotate_sh_rest
from ..transforms import matrix_to_quaternion, quaternion_multiply, quaternion_to_matrix
from .atomic import atomic_write
from .codec import SH_C0, Bytes, normalized_quats, sigmoid
from .ply import _F_REST_RE, _RESERVED, SplatArrays

__all__ = ["read_gltf", "sniff_gltf", "write_gltf"]

EXTENSION = "KHR_gaussian_splatting"
_PREFIX = EXTENSION + ":"
_GLB_MAGIC = b"glTF"
_JSON_CHUNK = 0x4E4F534A
_BIN_CHUNK = 0x004E4942
_ARRAY_BUFFER = 34962

#: glTF componentType -> little-endian numpy dtype.
_COMPONENT = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_CODE_OF = {np.dtype(v).newbyteorder("="): k for k, v in _COMPONENT.items() if k != 5125}
_NAMES = {5120: "signed byte", 5121: "unsigned byte", 5122: "signed short", 5123: "unsigned short",
          5125: "unsigned int", 5126: "float"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_FLOAT = 5126
_INTS = (5120, 5121, 5122, 5123)

#: (accessor type, allowed (componentType, normalized) pairs) of the extension's attributes.
_KINDS = {
    "POSITION": ("VEC3", {(_FLOAT, False)}),
    "ROTATION": ("VEC4", {(_FLOAT, False), (5120, True), (5122, True)}),
    "SCALE": ("VEC3", {(_FLOAT, False), (5121, False), (5121, True), (5123, False), (5123, True)}),
    "OPACITY": ("SCALAR", {(_FLOAT, False), (5121, True), (5123, True)}),
    "SH": ("VEC3", {(_FLOAT, False)}),
}
_QUANTIZED_POSITION = {(c, norm) for c in _INTS for norm in (False, True)}
_SUPPORTED_REQUIRED = {EXTENSION, "KHR_mesh_quantization"}

#: Sign of each sh_rest coefficient under the half turn about Z: (-1)^m.
_FLIP = np.array([(-1.0) ** m for band in (1, 2, 3) for m in range(-band, band + 1)], np.float32)
#: (w, x, y, z) of the half turn about Z and of its inverse.
_HALF_TURN = np.array([0.0, 0.0, 0.0, 1.0])
_HALF_TURN_INV = np.array([0.0, 0.0, 0.0, -1.0])
_P = np.diag([-1.0, -1.0, 1.0])

_TINY = float(np.finfo(np.float32).smallest_subnormal)  # 2^-149
_BELOW_ONE = 1.0 - 2.0 ** -24                             # largest float32 below 1


# --------------------------------------------------------------------------
# detection
# --------------------------------------------------------------------------

_ASSET_2 = re.compile(rb'"asset"\s*:\s*\{[^{}]*"version"\s*:\s*"2\.')


def sniff_gltf(head: bytes, path: str) -> bool:
    """A GLB header (``glTF``), or a JSON object naming ``asset.version`` 2.x
    (any JSON object when the name ends with ``.gltf``)."""
    if head[:4] == _GLB_MAGIC:
        return True
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if not text.startswith(b"{"):
        return False
    return bool(_ASSET_2.search(text)) or os.fspath(path).lower().endswith(".gltf")


# --------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------

class _Document:
    """A parsed glTF: its JSON, its buffers (loaded on demand) and error helpers."""

    def __init__(self, path: str, data: bytes):
        self.path = path
        self.base = os.path.dirname(os.path.abspath(path))
        self.bin = None
        if data[:4] == _GLB_MAGIC:
            self.json = self._parse_glb(data)
        elif data[:4096].lstrip(b"\xef\xbb\xbf \t\r\n")[:1] == b"{":
            self.json = self._parse_json(data, "file")
        else:
            raise self.error(f"not a glTF file: it starts with {data[:4]!r}, neither the GLB magic "
                             f"{_GLB_MAGIC!r} nor a JSON object")
        if not isinstance(self.json, dict):
            raise self.error("the glTF JSON is not an object")
        self._buffers: dict[int, memoryview] = {}

    def error(self, problem: str) -> SplatFormatError:
        return SplatFormatError(f"{self.path}: {problem}")

    def _parse_json(self, raw: bytes, where: str):
        try:
            return json.loads(raw.decode("utf-8-sig").rstrip(" \0"))
        except (UnicodeDecodeError, ValueError) as e:
            raise self.error(f"the {where} is not valid glTF JSON: {e}") from None

    def _parse_glb(self, data: bytes):
        b = Bytes(self.path, data, "GLB file")
        _, version, length = struct.unpack("<4sII", b.take(12, "the 12-byte GLB header"))
        if version != 2:
            raise self.error(f"GLB version {version}; only version 2 (glTF 2.0) is read")
        if length > len(data):
            raise self.error(
                f"truncated GLB file: its header says {length} bytes, the file has {len(data)}")
        if length < 20:
            raise self.error(f"GLB header length {length} is too small for a JSON chunk")
        b = Bytes(self.path, memoryview(data)[:length], "GLB file")
        b.pos = 12
        doc = None
        while b.left:
            clen, ctype = struct.unpack("<II", b.take(8, "a chunk header"))
            what = {_JSON_CHUNK: "the JSON chunk", _BIN_CHUNK: "the BIN chunk"}.get(ctype, f"chunk 0x{ctype:08x}")
            body = b.take(clen, what)
            if doc is None:
                if ctype != _JSON_CHUNK:
                    raise self.error(f"the first GLB chunk is 0x{ctype:08x}, not JSON")
                doc = self._parse_json(bytes(body), "JSON chunk")
            elif ctype == _BIN_CHUNK and self.bin is None:
                self.bin = body
        if doc is None:
            raise self.error("GLB file without a JSON chunk")
        return doc

    # -- JSON access with errors naming the place ---------------------------

    def items(self, key: str) -> list:
        value = self.json.get(key, [])
        if not isinstance(value, list):
            raise self.error(f"'{key}' is not an array")
        return value

    def item(self, key: str, index, where: str) -> dict:
        items = self.items(key)
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(items) \
                or not isinstance(items[index], dict):
            raise self.error(f"{where} refers to {key}[{index!r}], which does not exist ({len(items)} in the file)")
        return items[index]

    def buffer(self, index: int, where: str) -> memoryview:
        if index in self._buffers:
            return self._buffers[index]
        buf = self.item("buffers", index, where)
        length = _count(self, buf.get("byteLength"), f"buffers[{index}].byteLength")
        uri = buf.get("uri")
        if uri is None:
            if index != 0 or self.bin is None:
                raise self.error(f"buffers[{index}] has no uri and the file has no GLB BIN chunk for it")
            data = self.bin
        elif not isinstance(uri, str):
            raise self.error(f"buffers[{index}].uri is not a string")
        elif uri.startswith("data:"):
            header, _, payload = uri.partition(",")
            if not header.endswith(";base64"):
                raise self.error(f"buffers[{index}] has a data: URI that is not base64")
            try:
                data = memoryview(base64.b64decode(payload, validate=True))
            except (binascii.Error, ValueError) as e:
                raise self.error(f"buffers[{index}]: bad base64 in its data: URI ({e})") from None
        else:
            rel = urllib.parse.unquote(uri)
            if urllib.parse.urlsplit(uri).scheme or os.path.isabs(rel):
                raise self.error(f"buffers[{index}].uri {uri!r} is not a relative file name")
            file = os.path.join(self.base, rel)
            try:
                with open(file, "rb") as f:
                    data = memoryview(f.read())
            except OSError as e:
                raise self.error(f"buffers[{index}]: cannot read {file}: {e.strerror or e}") from None
        if len(data) < length:
            raise self.error(
                f"truncated buffers[{index}]: byteLength {length}, only {len(data)} bytes stored")
        self._buffers[index] = data[:length]
        return self._buffers[index]

    def view(self, index, offset: int, count: int, dtype: np.dtype, width: int, stride, where: str) -> np.ndarray:
        """``count`` rows of ``width`` ``dtype`` items from buffer view ``index``, ``offset`` bytes in."""
        bv = self.item("bufferViews", index, where)
        name = f"bufferViews[{index}]"
        buf = self.buffer(bv.get("buffer"), name)
        start = _count(self, bv.get("byteOffset", 0), f"{name}.byteOffset")
        length = _count(self, bv.get("byteLength"), f"{name}.byteLength")
        if start + length > len(buf):
            raise self.error(
                f"{name} (bytes {start}..{start + length}) runs past the end of its "
                f"{len(buf)}-byte buffer")
        element = dtype.itemsize * width
        stride = element if stride is None else stride
        if stride < element:
            raise self.error(f"{name}.byteStride {stride} is less than {where}'s {element}-byte element")
        need = offset + stride * (count - 1) + element if count else 0
        if need > length:
            raise self.error(
                f"{where} needs {need} bytes of {name}, which has {length} (truncated or inconsistent sizes)")
        if count == 0:
            return np.zeros((0, width), dtype.newbyteorder("="))
        rows = np.ndarray((count, width), dtype, buffer=buf, offset=start + offset, strides=(stride, dtype.itemsize))
        return rows.astype(dtype.newbyteorder("="))


def _count(doc: _Document, value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise doc.error(f"{what} is {value!r}, not a non-negative integer")
    return value


def _accessor(doc: _Document, index, what: str, kind: str | None, quantized_position: bool = False):
    """Accessor ``index`` as ``(values (count, width), componentType, normalized)``.

    ``kind`` (a key of ``_KINDS``) checks the type and component type and
    returns float32 as stored, integers as float64 (normalised ones decoded);
    ``None`` (an extra) returns a SCALAR in its stored dtype.
    """
    acc = doc.item("accessors", index, what)
    where = f"accessors[{index}] ({what})"
    ctype, atype, normalized = acc.get("componentType"), acc.get("type"), bool(acc.get("normalized", False))
    if ctype not in _COMPONENT:
        raise doc.error(f"{where} has unknown componentType {ctype!r}")
    if kind is None:
        allowed_type, allowed = "SCALAR", {(c, n) for c in _COMPONENT for n in (False, True)}
    else:
        allowed_type, allowed = _KINDS[kind]
        if kind == "POSITION" and quantized_position:
            allowed = allowed | _QUANTIZED_POSITION
    if atype != allowed_type:
        raise doc.error(f"{where} is {atype!r}; the attribute must be {allowed_type}")
    if (ctype, normalized) not in allowed:
        forms = ", ".join(sorted(f"{'normalized ' if n else ''}{_NAMES[c]}" for c, n in allowed))
        raise doc.error(
            f"{where} stores {'normalized ' if normalized else ''}{_NAMES[ctype]}; "
            f"the attribute allows {forms}")
    count = _count(doc, acc.get("count"), f"{where}.count")
    width = _WIDTH[atype]
    dtype = np.dtype(_COMPONENT[ctype])
    offset = _count(doc, acc.get("byteOffset", 0), f"{where}.byteOffset")
    if "bufferView" in acc:
        bv = doc.item("bufferViews", acc["bufferView"], where)
        stride = bv.get("byteStride")
        if stride is not None:
            stride = _count(doc, stride, f"bufferViews[{acc['bufferView']}].byteStride")
        values = doc.view(acc["bufferView"], offset, count, dtype, width, stride, where)
    else:
        if "sparse" not in acc:
            raise doc.error(f"{where} has neither a bufferView nor sparse values (compressed data?)")
        values = np.zeros((count, width), dtype.newbyteorder("="))
    sparse = acc.get("sparse")
    if sparse is not None:
        if not isinstance(sparse, dict) or not isinstance(sparse.get("indices"), dict) \
                or not isinstance(sparse.get("values"), dict):
            raise doc.error(f"{where}.sparse lacks indices or values")
        n = _count(doc, sparse.get("count"), f"{where}.sparse.count")
        ind, val = sparse["indices"], sparse["values"]
        itype = ind.get("componentType")
        if itype not in (5121, 5123, 5125):
            raise doc.error(f"{where}.sparse.indices.componentType {itype!r} is not an unsigned type")
        idx = doc.view(ind.get("bufferView"), _count(doc, ind.get("byteOffset", 0), f"{where}.sparse.indices"),
                       n, np.dtype(_COMPONENT[itype]), 1, None, f"{where}.sparse.indices")[:, 0]
        sub = doc.view(val.get("bufferView"), _count(doc, val.get("byteOffset", 0), f"{where}.sparse.values"),
                       n, dtype, width, None, f"{where}.sparse.values")
        if n and (np.any(np.diff(idx.astype(np.int64)) <= 0) or int(idx[-1]) >= count):
            raise doc.error(f"{where}.sparse.indices are not increasing indices below count {count}")
        values[idx.astype(np.int64)] = sub
    if kind is None:
        return values[:, 0], ctype, normalized
    if ctype == _FLOAT:
        return values, ctype, normalized
    out = values.astype(np.float64)
    if normalized:
        out = np.maximum(out / float(np.iinfo(dtype).max), -1.0)
    return out, ctype, normalized


def _node_matrix(doc: _Document, node: dict, where: str) -> np.ndarray:
    """The 4x4 local transform of a node (``matrix``, column-major, or T * R * S)."""
    try:
        if "matrix" in node:
            m = np.array(node["matrix"], np.float64)
            if m.shape != (16,):
                raise ValueError("matrix must have 16 numbers")
            return m.reshape(4, 4).T
        t = np.array(node.get("translation", [0.0, 0.0, 0.0]), np.float64)
        r = np.array(node.get("rotation", [0.0, 0.0, 0.0, 1.0]), np.float64)
        s = np.array(node.get("scale", [1.0, 1.0, 1.0]), np.float64)
        if t.shape != (3,) or r.shape != (4,) or s.shape != (3,):
            raise ValueError("translation, rotation and scale must have 3, 4 and 3 numbers")
    except (TypeError, ValueError) as e:
        raise doc.error(f"{where}: bad transform ({e})") from None
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(r[[3, 0, 1, 2]]) * s
    m[:3, 3] = t
    return m


def _instances(doc: _Document) -> list[tuple[int, np.ndarray, str]]:
    """``(mesh index, 4x4 global transform, where)`` of every mesh instance, in scene order."""
    nodes = doc.items("nodes")
    scenes = doc.items("scenes")
    if "scene" in doc.json or scenes:
        index = doc.json.get("scene", 0)
        roots = doc.item("scenes", index, "'scene'").get("nodes", [])
    elif nodes:
        children = {c for n in nodes if isinstance(n, dict) for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    else:
        return [(i, np.eye(4), f"meshes[{i}]") for i in range(len(doc.items("meshes")))]
    out = []
    stack = [(r, np.eye(4), ()) for r in reversed(roots)]
    while stack:
        index, parent, path = stack.pop()
        where = f"nodes[{index}]"
        if index in path:
            raise doc.error(f"{where} is its own ancestor (a cycle in the node hierarchy)")
        node = doc.item("nodes", index, "a scene or node")
        world = parent @ _node_matrix(doc, node, where)
        if "mesh" in node:
            out.append((node["mesh"], world, where))
        stack.extend((c, world, path + (index,)) for c in reversed(node.get("children", [])))
    return out


def _sh_degree(doc: _Document, attributes: dict, where: str) -> int:
    degree = 0
    for band in (1, 2, 3):
        have = [f"{_PREFIX}SH_DEGREE_{band}_COEF_{n}" in attributes for n in range(2 * band + 1)]
        if all(have) and degree == band - 1:
            degree = band
        elif any(have):
            raise doc.error(
                f"{where}: SH degree {band} is partially defined or a lower degree is missing "
                f"(the extension requires every coefficient of each degree up to the highest)")
    return degree


def _primitive(doc: _Document, prim: dict, where: str, quantized_position: bool) -> dict:
    """One splat primitive's arrays, in the file's (glTF) frame, float64 (extras as stored)."""
    mode = prim.get("mode", 4)
    if mode != 0:
        raise doc.error(f"{where}: mode is {mode}; a {EXTENSION} primitive must be POINTS (0)")
    ext = prim["extensions"][EXTENSION]
    if isinstance(ext, dict) and ext.get("extensions"):
        raise doc.error(
            f"{where}: the splats are encoded by {', '.join(ext['extensions'])}, which this reader does not decode")
    attributes = prim.get("attributes")
    if not isinstance(attributes, dict):
        raise doc.error(f"{where} has no attributes")
    required = {"POSITION": "POSITION", "ROTATION": _PREFIX + "ROTATION", "SCALE": _PREFIX + "SCALE",
                "OPACITY": _PREFIX + "OPACITY", "DC": _PREFIX + "SH_DEGREE_0_COEF_0"}
    missing = [name for name in required.values() if name not in attributes]
    if missing:
        raise doc.error(f"{where} lacks the attribute(s) {', '.join(missing)}")

    def get(name, kind):
        return _accessor(doc, attributes[name], f"{where} {name}", kind, quantized_position)

    means, _, _ = get("POSITION", "POSITION")
    n = len(means)
    out = {"means": means}
    out["quats"] = get(required["ROTATION"], "ROTATION")[0][:, [3, 0, 1, 2]]
    out["scales"], scale_type, scale_norm = get(required["SCALE"], "SCALE")
    out["log_scales"] = scale_type == _FLOAT and bool(np.any(out["scales"] < 0))
    out["alpha"] = get(required["OPACITY"], "OPACITY")[0][:, 0]
    out["sh_dc"] = get(required["DC"], "SH")[0]
    degree = _sh_degree(doc, attributes, where)
    names = [f"{_PREFIX}SH_DEGREE_{band}_COEF_{c}" for band in range(1, degree + 1) for c in range(2 * band + 1)]
    out["sh_rest"] = np.zeros((n, len(names), 3), np.float32)
    for k, name in enumerate(names):
        coef = get(name, "SH")[0]
        if len(coef) != n:
            raise doc.error(f"{where}: POSITION has {n} elements but {name} has {len(coef)}")
        out["sh_rest"][:, k] = coef
    extra = {}
    for name in attributes:
        if name.startswith("_"):
            acc = doc.item("accessors", attributes[name], f"{where} {name}")
            if acc.get("type") != "SCALAR":
                warnings.warn(f"{doc.path}: {where} {name} is {acc.get('type')}, not SCALAR: not read", UserWarning,
                              stacklevel=4)
                continue
            values, ctype, normalized = _accessor(doc, attributes[name], f"{where} {name}", None)
            if normalized and ctype != _FLOAT:
                values = np.maximum(values / float(np.iinfo(values.dtype).max), -1.0).astype(np.float32)
            key = name[1:]
            extra[name if key in _RESERVED or _F_REST_RE.match(key) else key] = values
        elif name.startswith(_PREFIX) and name not in required.values() and not re.fullmatch(
                re.escape(_PREFIX) + r"SH_DEGREE_[1-3]_COEF_\d", name):
            warnings.warn(f"{doc.path}: {where} has the unknown attribute {name}; ignored", UserWarning, stacklevel=4)
    out["extra"] = extra
    for key in ("quats", "scales", "alpha", "sh_dc"):
        if len(out[key]) != n:
            raise doc.error(f"{where}: POSITION has {n} elements but the {key} accessor has {len(out[key])}")
    for name, values in extra.items():
        if len(values) != n:
            raise doc.error(f"{where}: POSITION has {n} elements but the _{name} accessor has {len(values)}")
    return out


def _to_ply_frame(doc: _Document, p: dict, world: np.ndarray, where: str) -> None:
    """Apply the node transform ``world`` and the glTF -> PLY half turn to ``p`` in place."""
    if p["log_scales"]:
        warnings.warn(
            f"{doc.path}: {where} stores negative KHR_gaussian_splatting:SCALE values: read as log scales "
            "(the extension's pre-ratification draft; the ratified extension stores linear scales)",
            UserWarning, stacklevel=4)
        log_scales = p["scales"]
    else:
        log_scales = np.log(np.maximum(p["scales"].astype(np.float64), _TINY))
    k1 = p["sh_rest"].shape[1]
    if np.array_equal(world, np.eye(4)):
        p["means"] = p["means"] * np.diag(_P)
        p["quats"] = quaternion_multiply(_HALF_TURN_INV, p["quats"])
        p["sh_rest"] = p["sh_rest"] * _FLIP[:k1, None]
        p["scales"] = log_scales
        return
    a = _P @ world[:3, :3]
    if not np.all(np.isfinite(world)) or not np.linalg.det(a) > 0:
        raise doc.error(f"{where}: its transform is singular or mirrors; the extension leaves such splats undefined")
    u, sv, vt = np.linalg.svd(a)
    rot = u @ vt
    p["means"] = p["means"] @ a.T + _P @ world[:3, 3]
    if sv[0] - sv[-1] <= 1e-7 * sv[0]:
        p["quats"] = quaternion_multiply(matrix_to_quaternion(rot), p["quats"])
        p["scales"] = log_scales + np.log(sv.mean())
    else:
        # Covariance M C C^T M^T with C = R(q) diag(exp s): its SVD gives the new axes and scales.
        c = a @ quaternion_to_matrix(p["quats"]) * np.exp(log_scales)[:, None, :]
        cu, cs, _ = np.linalg.svd(c)
        cu[np.linalg.det(cu) < 0, :, 2] *= -1.0
        p["quats"] = matrix_to_quaternion(cu)
        p["scales"] = np.log(np.maximum(cs, _TINY))
    if k1:
        p["sh_rest"] = rotate_sh_rest(p["sh_rest"].astype(np.float64), rot)


def read_gltf(path: str | os.PathLike) -> SplatArrays:
    """Read the splats of a ``.glb`` / ``.gltf`` file into :class:`SplatArrays` (PLY frame).

    Raises :class:`SplatFormatError` naming the file for a truncated or
    malformed file, one without a ``KHR_gaussian_splatting`` primitive, or
    one needing an extension this reader does not decode.
    """
    path = os.fspath(path)
    with open(path, "rb") as f:
        data = f.read()
    if not data:
        raise SplatFormatError(f"{path}: empty file (0 bytes)")
    doc = _Document(path, data)
    asset = doc.json.get("asset")
    version = asset.get("version") if isinstance(asset, dict) else None
    if not isinstance(version, str) or not version.startswith("2."):
        raise doc.error(f"asset.version is {version!r}; only glTF 2.x is read")
    unsupported = [e for e in doc.items("extensionsRequired") if e not in _SUPPORTED_REQUIRED]
    if unsupported:
        raise doc.error(f"the file requires the extension(s) {', '.join(map(str, unsupported))}, "
                        "which this reader does not support")
    quantized = "KHR_mesh_quantization" in doc.items("extensionsUsed")

    parts = []
    for mesh_index, world, where in _instances(doc):
        mesh = doc.item("meshes", mesh_index, where)
        prims = mesh.get("primitives", [])
        for k, prim in enumerate(prims if isinstance(prims, list) else []):
            if isinstance(prim, dict) and isinstance(prim.get("extensions"), dict) \
                    and EXTENSION in prim["extensions"]:
                w = f"meshes[{mesh_index}].primitives[{k}] (instanced by {where})"
                p = _primitive(doc, prim, w, quantized)
                _to_ply_frame(doc, p, world, w)
                parts.append(p)
    if not parts:
        raise doc.error(f"no mesh primitive of the scene has the {EXTENSION} extension")

    k1 = max(p["sh_rest"].shape[1] for p in parts)
    names = [name for name in parts[0]["extra"] if all(name in p["extra"] for p in parts)]
    dropped = sorted({name for p in parts for name in p["extra"]} - set(names))
    if dropped:
        warnings.warn(f"{path}: extra attributes not in every splat primitive are not read: {', '.join(dropped)}",
                      UserWarning, stacklevel=2)

    def cat(values: list) -> np.ndarray:
        return (values[0] if len(values) == 1 else np.concatenate(values)).astype(np.float32, copy=False)

    rest = [p["sh_rest"] if p["sh_rest"].shape[1] == k1 else
            np.pad(p["sh_rest"], ((0, 0), (0, k1 - p["sh_rest"].shape[1]), (0, 0))) for p in parts]
    a = np.clip(cat([p["alpha"] for p in parts]).astype(np.float64), _TINY, _BELOW_ONE)
    n = len(a)
    return SplatArrays(
        means=cat([p["means"] for p in parts]),
        scales=cat([p["scales"] for p in parts]),
        quats=cat([p["quats"] for p in parts]),
        opacities=np.log(a / (1.0 - a)).astype(np.float32),
        sh_dc=cat([p["sh_dc"] for p in parts]).reshape(n, 1, 3),
        sh_rest=cat(rest),
        extra={name: np.concatenate([p["extra"][name] for p in parts]) for name in names},
    )


# --------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------

def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _document(splats: SplatArrays, path: str) -> tuple[dict, bytes]:
    """The glTF JSON (without the buffer's uri) and buffer 0 for ``splats``."""
    n = splats.count
    if n == 0:
        raise SplatFormatError(f"{path}: glTF cannot hold zero splats (an accessor's count must be at least 1)")
    means = np.asarray(splats.means, np.float32) * np.float32([-1, -1, 1])
    q = quaternion_multiply(_HALF_TURN, normalized_quats(splats.quats))
    dc = np.asarray(splats.sh_dc, np.float32).reshape(n, 3)
    rest = np.asarray(splats.sh_rest, np.float32)
    k1 = rest.shape[1]
    alpha = sigmoid(splats.opacities)
    with np.errstate(over="ignore", invalid="ignore"):
        rgb = _srgb_to_linear(np.clip(0.5 + SH_C0 * dc.astype(np.float64), 0.0, 1.0))
        color = np.nan_to_num(np.concatenate([rgb, alpha[:, None]], axis=1) * 255.0)
        scales = np.exp(np.asarray(splats.scales, np.float64)).astype(np.float32)
    finite = means[np.isfinite(means).all(axis=1)]
    bounds = (finite.min(axis=0), finite.max(axis=0)) if len(finite) else (np.zeros(3), np.zeros(3))

    # (semantic, data (n, width) or (n,), accessor type, extra accessor fields)
    attrs = [
        ("POSITION", means, "VEC3", {"min": [float(v) for v in bounds[0]], "max": [float(v) for v in bounds[1]]}),
        ("COLOR_0", np.clip(np.rint(color), 0, 255).astype(np.uint8), "VEC4", {"normalized": True}),
        (_PREFIX + "ROTATION", q[:, [1, 2, 3, 0]].astype(np.float32), "VEC4", {}),
        (_PREFIX + "SCALE", scales, "VEC3", {}),
        (_PREFIX + "OPACITY", alpha.astype(np.float32), "SCALAR", {}),
        (_PREFIX + "SH_DEGREE_0_COEF_0", dc, "VEC3", {}),
    ]
    flipped = rest * _FLIP[:k1, None]
    k = 0
    for band in range(1, {0: 0, 3: 1, 8: 2, 15: 3}[k1] + 1):
        for c in range(2 * band + 1):
            attrs.append((f"{_PREFIX}SH_DEGREE_{band}_COEF_{c}", flipped[:, k], "VEC3", {}))
            k += 1
    skipped = []
    for name, values in splats.extra.items():
        values = np.asarray(values)
        code = _CODE_OF.get(values.dtype.newbyteorder("="))
        if code is None:
            skipped.append(f"{name} ({values.dtype})")
        else:
            attrs.append(("_" + name, values, "SCALAR", {}))
    if skipped:
        warnings.warn(
            f"{path}: glTF attributes hold float32, int8, uint8, int16 and uint16 only; the extra "
            f"properties {', '.join(skipped)} are not written", UserWarning, stacklevel=3)

    chunks, views, accessors, attributes = [], [], [], {}
    offset = 0
    for i, (semantic, values, atype, fields) in enumerate(attrs):
        dt = values.dtype.newbyteorder("<")
        view = {"buffer": 0, "byteOffset": offset, "target": _ARRAY_BUFFER}
        if dt.itemsize < 4 and atype == "SCALAR":
            # Vertex attribute elements must start on 4-byte boundaries: one per 4-byte slot.
            padded = np.zeros((n, 4 // dt.itemsize), dt)
            padded[:, 0] = values
            raw = padded.tobytes()
            view["byteStride"] = 4
        else:
            raw = np.ascontiguousarray(values, dt).tobytes()
        view["byteLength"] = len(raw)
        chunks.append(raw)
        offset += len(raw)
        views.append(view)
        accessors.append({"bufferView": i, "componentType": _CODE_OF[dt.newbyteorder("=")],
                          "count": n, "type": atype, **fields})
        attributes[semantic] = i
    doc = {
        "asset": {"version": "2.0", "generator": f"mlx3d {__version__}"},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": attributes,
            "mode": 0,
            "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                                       "projection": "perspective", "sortingMethod": "cameraDistance"}},
        }]}],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": accessors,
    }
    return doc, b"".join(chunks)


def write_gltf(path: str | os.PathLike, splats: SplatArrays, *, fsync: bool = True) -> None:
    """Write ``splats`` as ``.glb`` (a ``.gltf`` name: JSON with a base64 buffer), atomically.

    Raises :class:`SplatFormatError` for zero splats (glTF accessors cannot
    be empty); warns naming extras of a dtype glTF cannot hold.
    """
    path = os.fspath(path)
    doc, buffer = _document(splats, path)
    if path.lower().endswith(".gltf"):
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(buffer).decode("ascii")
        content = json.dumps(doc, allow_nan=False, indent=1).encode("utf-8")
    else:
        text = json.dumps(doc, allow_nan=False, separators=(",", ":")).encode("utf-8")
        text += b" " * (-len(text) % 4)
        content = b"".join([
            struct.pack("<4sII", _GLB_MAGIC, 2, 12 + 8 + len(text) + 8 + len(buffer)),
            struct.pack("<II", len(text), _JSON_CHUNK), text,
            struct.pack("<II", len(buffer), _BIN_CHUNK), buffer,
        ])
    with atomic_write(path, "wb", fsync=fsync) as f:
        f.write(content)
