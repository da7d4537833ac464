"""glTF ``KHR_gaussian_splatting`` (.glb / .gltf): files built by hand from the
extension's specification, node transforms, round trips within the bounds of
mlx3d/io/gltf.py, the structure of our files (and the Khronos validator where
installed), files written by the peer, bad files, detection.

splat-transform writes .glb but does not read it, so the peer direction is its
files read by us, and its file and ours from the same PLY compared attribute
by attribute.  ``data/formats/opensplat_500_sh1.glb`` was made with
``splat-transform tests/data/formats/opensplat_500.ply -H 1 tests/data/formats/opensplat_500_sh1.glb``
(3.7.0).
"""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import struct
import subprocess

import numpy as np
import pytest

from format_cases import DATA, REAL_PLY, adversarial_splats, assert_close_splats, real_splats, rotations
from format_cases import splat_transform  # noqa: F401
from mlx3d.errors import SplatFormatError
from mlx3d.io import NORMAL_NAMES, SplatArrays, read_splat_ply, read_splats, write_splat_ply, write_splats
from mlx3d.io.codec import SH_C0
from mlx3d.io.gltf import sniff_gltf
from peer import REPO

PEER_GLB = DATA / "opensplat_500_sh1.glb"
K = "KHR_gaussian_splatting:"
P = np.diag([-1.0, -1.0, 1.0])  # glTF axes <-> PLY axes (a half turn about Z)
F32 = {5126: "<f4", 5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4"}

# The module's stated bounds.
BOUNDS = dict(means=0.0, sh_dc=0.0, sh_rest=0.0, rotation=1e-6, alpha=6e-8)


# --------------------------------------------------------------------------
# GLB files built here with json + struct, from the glTF and extension specs
# --------------------------------------------------------------------------

def glb_bytes(doc: dict, binary: bytes) -> bytes:
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    return (struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(binary))
            + struct.pack("<II", len(text), 0x4E4F534A) + text
            + struct.pack("<II", len(binary), 0x004E4942) + binary)


def parse_glb(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == 0x4E4F534A and jlen % 4 == 0
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == 0x004E4942 and blen % 4 == 0 and 28 + jlen + blen == len(data)
    return doc, data[28 + jlen:]


def accessor_values(doc: dict, binary: bytes, index: int) -> np.ndarray:
    """A tightly packed or strided accessor, read as the glTF spec says."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    dt = np.dtype(F32[acc["componentType"]])
    stride = view.get("byteStride", dt.itemsize * width)
    start = view["byteOffset"] + acc.get("byteOffset", 0)
    rows = [np.frombuffer(binary, dt, width, start + i * stride) for i in range(acc["count"])]
    return np.array(rows)


class Builder:
    """A glTF document whose accessors are appended one buffer view each."""

    def __init__(self):
        self.binary = bytearray()
        self.doc = {"asset": {"version": "2.0"}, "extensionsUsed": ["KHR_gaussian_splatting"],
                    "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
                    "meshes": [{"primitives": [{"mode": 0, "attributes": {},
                                                "extensions": {"KHR_gaussian_splatting": {
                                                    "kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}}]}],
                    "buffers": [{"byteLength": 0}], "bufferViews": [], "accessors": []}

    def view(self, raw: bytes, **fields) -> int:
        self.binary += b"\0" * (-len(self.binary) % 4)
        self.doc["bufferViews"].append({"buffer": 0, "byteOffset": len(self.binary), "byteLength": len(raw), **fields})
        self.binary += raw
        self.doc["buffers"][0]["byteLength"] = len(self.binary)
        return len(self.doc["bufferViews"]) - 1

    def attribute(self, name, values, ctype=5126, atype=None, **fields) -> int:
        values = np.asarray(values)
        atype = atype or {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[1 if values.ndim == 1 else values.shape[1]]
        view = self.view(values.astype(F32[ctype]).tobytes())
        self.doc["accessors"].append({"bufferView": view, "componentType": ctype, "count": len(values),
                                      "type": atype, **fields})
        index = len(self.doc["accessors"]) - 1
        if name:
            self.prim["attributes"][name] = index
        return index

    @property
    def prim(self) -> dict:
        return self.doc["meshes"][0]["primitives"][0]

    def glb(self) -> bytes:
        return glb_bytes(self.doc, bytes(self.binary))


def two_splats(b: Builder | None = None, degree: int = 1) -> Builder:
    """Two splats in the glTF frame, every value chosen by hand."""
    b = b or Builder()
    b.attribute("POSITION", [[1.0, 2.0, 3.0], [-4.0, 5.0, -6.0]], min=[-4, 2, -6], max=[1, 5, 3])
    h = math.sqrt(0.5)
    b.attribute(K + "ROTATION", [[0.0, 0.0, 0.0, 1.0], [h, 0.0, 0.0, h]])       # x y z w
    b.attribute(K + "SCALE", [[0.5, 1.0, 2.0], [1.0, 0.25, 4.0]])
    b.attribute(K + "OPACITY", [0.25, 0.75])
    b.attribute(K + "SH_DEGREE_0_COEF_0", [[0.1, 0.2, 0.3], [-1.0, 0.0, 1.0]])
    for band in range(1, degree + 1):
        for c in range(2 * band + 1):
            b.attribute(f"{K}SH_DEGREE_{band}_COEF_{c}", [[band, c, 1.0], [-c, band, 2.0]])
    return b


def sh1_colour(rest: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Degree-1 SH colour part (spec: Y1,-1 = -C1 y, Y1,0 = C1 z, Y1,1 = -C1 x) along unit ``d``."""
    c1 = 0.4886025119029199
    x, y, z = d
    return -c1 * y * rest[:, 0] + c1 * z * rest[:, 1] - c1 * x * rest[:, 2]


def test_hand_built_glb_from_the_specification(tmp_path):
    path = tmp_path / "two.glb"
    path.write_bytes(two_splats().glb())
    s = read_splats(path)
    assert s.count == 2 and s.sh_degree == 1 and s.extra == {}
    # Positions: the half turn about Z, exact.
    np.testing.assert_array_equal(s.means, [[-1, -2, 3], [4, -5, -6]])
    np.testing.assert_allclose(s.scales, np.log([[0.5, 1.0, 2.0], [1.0, 0.25, 4.0]]), atol=1e-7)
    np.testing.assert_allclose(1 / (1 + np.exp(-s.opacities.astype(np.float64))), [0.25, 0.75], atol=6e-8)
    np.testing.assert_allclose(s.sh_dc[:, 0], [[0.1, 0.2, 0.3], [-1.0, 0.0, 1.0]], atol=0)
    # Rotations: the splats turn with the scene, R_ply = P R_gltf; the second
    # is a quarter turn about glTF's x.
    quarter_x = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]])
    np.testing.assert_allclose(rotations(s.quats), [P, P @ quarter_x], atol=1e-7)
    # SH: m = -1 and m = +1 change sign, m = 0 does not; the colour seen along
    # P d in the PLY frame is the one seen along d in the file.
    np.testing.assert_array_equal(s.sh_rest[:, :, 0], [[-1, 1, -1], [0, -1, 2]])
    for d in np.eye(3).tolist() + [[0.6, 0.0, 0.8]]:
        d = np.array(d)
        file_rest = np.array([[[1, 0, 1], [1, 1, 1], [1, 2, 1]], [[0, 1, 2], [-1, 1, 2], [-2, 1, 2]]], float)
        np.testing.assert_allclose(sh1_colour(s.sh_rest, P @ d), sh1_colour(file_rest, d), atol=1e-7)


def test_accessor_forms_integers_strides_sparse_and_gltf_buffers(tmp_path):
    b = two_splats(degree=0)
    # POSITION and DC interleaved in one view (stride 24, the second at byteOffset 12).
    pos = np.array([[1.0, 2.0, 3.0], [-4.0, 5.0, -6.0]], "<f4")
    dc = np.array([[0.1, 0.2, 0.3], [-1.0, 0.0, 1.0]], "<f4")
    view = b.view(np.concatenate([pos, dc], axis=1).tobytes(), byteStride=24, target=34962)
    b.doc["accessors"] += [
        {"bufferView": view, "componentType": 5126, "count": 2, "type": "VEC3", "min": [-4, 2, -6], "max": [1, 5, 3]},
        {"bufferView": view, "byteOffset": 12, "componentType": 5126, "count": 2, "type": "VEC3"}]
    n_acc = len(b.doc["accessors"])
    b.prim["attributes"]["POSITION"] = n_acc - 2
    b.prim["attributes"][K + "SH_DEGREE_0_COEF_0"] = n_acc - 1
    # Integer forms the extension allows: normalised int16 rotation, unsigned
    # short scale (not normalised), normalised uint8 opacity.
    b.attribute(K + "ROTATION", [[0, 0, 0, 32767], [-32768, 0, 0, 0]], 5122, normalized=True)
    b.attribute(K + "SCALE", [[1, 2, 3], [4, 5, 6]], 5123)
    b.attribute(K + "OPACITY", [255, 51], 5121, normalized=True)
    # A sparse accessor over zeros (no bufferView): the extra _label, splat 1 only.
    idx = b.view(np.array([1], "<u2").tobytes())
    val = b.view(np.array([7.5], "<f4").tobytes())
    b.doc["accessors"].append({"componentType": 5126, "count": 2, "type": "SCALAR", "sparse": {
        "count": 1, "indices": {"bufferView": idx, "componentType": 5123}, "values": {"bufferView": val}}})
    b.prim["attributes"]["_label"] = len(b.doc["accessors"]) - 1
    b.attribute("_class", [3, 250], 5121)  # tightly packed bytes: read all the same

    path = tmp_path / "forms.glb"
    path.write_bytes(b.glb())
    s = read_splats(path)
    np.testing.assert_array_equal(s.means, [[-1, -2, 3], [4, -5, -6]])
    np.testing.assert_array_equal(s.sh_dc[:, 0], dc)
    np.testing.assert_allclose(s.scales, np.log([[1, 2, 3], [4, 5, 6]]), atol=1e-7)
    np.testing.assert_allclose(1 / (1 + np.exp(-s.opacities.astype(np.float64))), [1 - 2 ** -24, 0.2], atol=6e-8)
    # int16 -32768 reads as -1 (clamped, as glTF says): a half turn about x.
    np.testing.assert_allclose(rotations(s.quats), [P, P @ np.diag([1.0, -1, -1])], atol=1e-7)
    np.testing.assert_array_equal(s.extra["label"], [0.0, 7.5])
    assert s.extra["class"].dtype == np.uint8 and s.extra["class"].tolist() == [3, 250]

    # The same document as .gltf: buffer as a base64 data: URI, then as a .bin file beside it.
    doc, binary = parse_glb(path.read_bytes())
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
    (tmp_path / "embedded.gltf").write_text(json.dumps(doc))
    doc["buffers"][0]["uri"] = "sub%20dir/data.bin"
    (tmp_path / "sub dir").mkdir()
    (tmp_path / "sub dir" / "data.bin").write_bytes(binary)
    (tmp_path / "external.gltf").write_text(json.dumps(doc))
    for name in ("embedded.gltf", "external.gltf"):
        g = read_splats(tmp_path / name)
        for key in ("means", "scales", "quats", "opacities", "sh_dc"):
            np.testing.assert_array_equal(getattr(g, key), getattr(s, key), err_msg=f"{name} {key}")


def cov(s: SplatArrays) -> np.ndarray:
    """``(N, 3, 3)`` covariances ``R diag(exp(2 s)) R^T``."""
    r = rotations(s.quats)
    return r * np.exp(2 * s.scales.astype(np.float64))[:, None, :] @ r.transpose(0, 2, 1)


def _node_case(tmp_path, nodes, name):
    b = two_splats()
    b.doc["nodes"] = nodes
    path = tmp_path / name
    path.write_bytes(b.glb())
    return read_splats(path), read_splats(tmp_path / "plain.glb")


@pytest.mark.parametrize("kind", ["trs", "matrix-nonuniform", "nested"])
def test_node_transforms_are_applied(tmp_path, kind):
    (tmp_path / "plain.glb").write_bytes(two_splats().glb())
    angle = 0.7
    c, s_ = math.cos(angle / 2), math.sin(angle / 2)
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    rot = {"rotation": [*(axis * s_), c]}  # x y z w
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rmat = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    if kind == "trs":
        nodes = [{"mesh": 0, "translation": [1.0, -2.0, 0.5], "scale": [2.0, 2.0, 2.0], **rot}]
        lin, t = 2.0 * rmat, np.array([1.0, -2.0, 0.5])
    elif kind == "matrix-nonuniform":
        lin, t = rmat @ np.diag([1.0, 3.0, 0.5]), np.array([0.0, 4.0, 0.0])
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = lin, t
        nodes = [{"mesh": 0, "matrix": m.T.ravel().tolist()}]
    else:
        nodes = [{"children": [1], "translation": [0.0, 0.0, 3.0]}, {"mesh": 0, **rot}]
        lin, t = rmat, np.array([0.0, 0.0, 3.0])
    got, plain = _node_case(tmp_path, nodes, f"{kind}.glb")
    a = P @ lin @ P  # the node's map, in PLY axes
    np.testing.assert_allclose(got.means, plain.means @ a.T + P @ t, atol=1e-5)
    # Covariances: A Sigma A^T.
    np.testing.assert_allclose(cov(got), a @ cov(plain) @ a.T, atol=1e-5 * np.abs(cov(got)).max())
    # SH follow the rotation part R of A: colour along R d equals the file's along d.
    u, _, vt = np.linalg.svd(a)
    r = u @ vt
    for d in np.random.default_rng(0).normal(size=(5, 3)):
        d /= np.linalg.norm(d)
        np.testing.assert_allclose(sh1_colour(got.sh_rest, r @ d), sh1_colour(plain.sh_rest, d), atol=1e-6)
    np.testing.assert_array_equal(got.sh_dc, plain.sh_dc)
    np.testing.assert_array_equal(got.opacities, plain.opacities)


def test_degree_3_rotation_keeps_the_colour_seen_from_each_direction(tmp_path):
    sh = pytest.importorskip("mlx3d.splatting.sh", reason="mlx3d.splatting.sh needs MLX")
    b = Builder()
    two_splats(b, degree=3)
    b.doc["nodes"] = [{"mesh": 0, "rotation": [0.2, -0.4, 0.1, math.sqrt(1 - 0.21)]}]
    (tmp_path / "rot.glb").write_bytes(b.glb())
    (tmp_path / "plain.glb").write_bytes(two_splats(degree=3).glb())
    got, plain = read_splats(tmp_path / "rot.glb"), read_splats(tmp_path / "plain.glb")
    x, y, z, w = 0.2, -0.4, 0.1, math.sqrt(1 - 0.21)
    r = P @ rotations(np.array([[w, x, y, z]]))[0] @ P
    # The oracle is the invariance colour(R d) == colour(d), evaluated with the renderer's SH.
    dirs = np.random.default_rng(0).normal(size=(64, 3))
    for i in range(got.count):
        rotated = np.concatenate([got.sh_dc[i], got.sh_rest[i]]).astype(np.float64)
        original = np.concatenate([plain.sh_dc[i], plain.sh_rest[i]]).astype(np.float64)
        np.testing.assert_allclose(sh.eval_sh(3, rotated[None], dirs @ r.T), sh.eval_sh(3, original[None], dirs), atol=1e-5)


def test_multiple_primitives_and_instances_are_concatenated(tmp_path):
    b = two_splats(degree=1)
    prim = b.prim
    lone = {"mode": 0, "attributes": {k: v for k, v in prim["attributes"].items() if "DEGREE_1" not in k},
            "extensions": prim["extensions"]}
    b.doc["meshes"].append({"primitives": [lone]})
    b.doc["nodes"] = [{"mesh": 0}, {"mesh": 1, "translation": [10.0, 0.0, 0.0]}, {"mesh": 0}]
    b.doc["scenes"] = [{"nodes": [0, 1, 2]}]
    path = tmp_path / "many.glb"
    path.write_bytes(b.glb())
    s = read_splats(path)
    assert s.count == 6 and s.sh_degree == 1
    np.testing.assert_array_equal(s.means[2:4], s.means[:2] + [-10, 0, 0])
    np.testing.assert_array_equal(s.sh_rest[2:4], 0)
    np.testing.assert_array_equal(s.sh_rest[4:], s.sh_rest[:2])


def test_legacy_log_scales_are_read_with_a_warning(tmp_path):
    b = Builder()
    two_splats(b, degree=0)
    log = np.array([[-1.0, 0.5, -3.0], [0.0, 0.0, -0.1]])
    b.doc["accessors"][b.prim["attributes"][K + "SCALE"]]["bufferView"] = b.view(log.astype("<f4").tobytes())
    path = tmp_path / "draft.glb"
    path.write_bytes(b.glb())
    with pytest.warns(UserWarning, match="negative.*log scales"):
        s = read_splats(path)
    np.testing.assert_array_equal(s.scales, log.astype(np.float32))


# --------------------------------------------------------------------------
# round trips and the structure of our files
# --------------------------------------------------------------------------

def _check_activations(got: SplatArrays, want: SplatArrays, what: str) -> None:
    s = want.scales.astype(np.float64)
    bound = 6e-8 + np.spacing(np.abs(want.scales)).astype(np.float64) / 2
    assert np.all(np.abs(got.scales - s) <= bound), f"{what}: scales"
    l = want.opacities.astype(np.float64)
    lb = 6e-8 * (1 + np.exp(np.minimum(l, 16.6))) + np.spacing(np.abs(want.opacities)).astype(np.float64) / 2
    ok = np.abs(got.opacities - np.minimum(l, 16.6355)) <= lb
    assert np.all(ok), f"{what}: opacity logits, worst at {l[~ok][:3]}"


@pytest.mark.parametrize("case", ["real", "adversarial", "degree0"])
def test_round_trip_within_bounds(tmp_path, case):
    src = {"real": real_splats, "degree0": lambda: real_splats(0),
           "adversarial": lambda: adversarial_splats(span=1e4)}[case]()
    path = tmp_path / "a.glb"
    write_splats(path, src)
    got = read_splats(path)
    assert_close_splats(got, src, scales=2e-6, **BOUNDS, what=case)
    np.testing.assert_array_equal(got.means, src.means)
    np.testing.assert_array_equal(got.sh_rest, src.sh_rest)
    _check_activations(got, src, case)
    # The .gltf form holds the same.
    write_splats(tmp_path / "a.gltf", src)
    g2 = read_splats(tmp_path / "a.gltf")
    for key in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(g2, key), getattr(got, key), err_msg=key)


def test_extreme_activations(tmp_path):
    src = adversarial_splats(n=8, degree=0)
    src.scales[:] = [[-87.0, 88.0, 0.0]]
    src.opacities[:] = [-80.0, -20.0, 0.0, 5.0, 12.0, 16.0, 17.0, 40.0]
    write_splats(tmp_path / "x.glb", src)
    got = read_splats(tmp_path / "x.glb")
    _check_activations(got, src, "extreme")
    assert np.all(np.isfinite(got.opacities)) and got.opacities.max() == pytest.approx(16.6355, abs=1e-4)


def test_extras_round_trip_or_are_named(tmp_path):
    src = real_splats(1)
    n = src.count
    src.extra.update(confidence=np.linspace(0, 1, n, dtype=np.float32), segment=np.arange(n, dtype=np.int16) - 7,
                     flag=(np.arange(n) % 3).astype(np.uint8), x_=np.full(n, -1, np.int8),
                     wide=np.zeros(n, np.float64))
    with pytest.warns(UserWarning, match=r"wide \(float64\)"):
        write_splats(tmp_path / "e.glb", src)
    got = read_splats(tmp_path / "e.glb")
    assert list(got.extra) == ["confidence", "segment", "flag", "x_"]
    for name, values in got.extra.items():
        assert values.dtype == src.extra[name].dtype
        np.testing.assert_array_equal(values, src.extra[name])
    # What we read back is written as a PLY unchanged (which adds its normals).
    write_splats(tmp_path / "e.ply", got)
    assert [k for k in read_splat_ply(tmp_path / "e.ply").extra if k not in NORMAL_NAMES] == list(got.extra)


def test_structure_of_our_glb(tmp_path):
    src = real_splats()
    src.extra["tag"] = np.arange(src.count, dtype=np.uint8)
    path = tmp_path / "s.glb"
    write_splats(path, src)
    doc, binary = parse_glb(path.read_bytes())
    assert doc["asset"]["version"] == "2.0"
    assert "KHR_gaussian_splatting" in doc["extensionsUsed"] and "extensionsRequired" not in doc
    assert doc["buffers"] == [{"byteLength": len(binary)}]
    nodes = [doc["nodes"][i] for i in doc["scenes"][doc["scene"]]["nodes"]]
    assert nodes == [{"mesh": 0}]  # no node transform: the values are in glTF axes
    (prim,) = doc["meshes"][0]["primitives"]
    assert prim["mode"] == 0
    ext = prim["extensions"]["KHR_gaussian_splatting"]
    assert ext["kernel"] == "ellipse" and ext["colorSpace"] == "srgb_rec709_display"
    attrs = prim["attributes"]
    sh = [f"{K}SH_DEGREE_{d}_COEF_{c}" for d in range(4) for c in range(2 * d + 1)]
    assert set(attrs) == {"POSITION", "COLOR_0", K + "ROTATION", K + "SCALE", K + "OPACITY", "_tag", *sh}
    for view in doc["bufferViews"]:
        assert view["byteOffset"] % 4 == 0 and view.get("byteStride", 4) % 4 == 0
        assert view["byteOffset"] + view["byteLength"] <= len(binary)
    for acc in doc["accessors"]:
        assert acc["count"] == src.count and acc.get("byteOffset", 0) % 4 == 0
    pos = accessor_values(doc, binary, attrs["POSITION"])
    acc = doc["accessors"][attrs["POSITION"]]
    assert acc["componentType"] == 5126 and acc["type"] == "VEC3"
    np.testing.assert_array_equal(acc["min"], pos.min(axis=0))
    np.testing.assert_array_equal(acc["max"], pos.max(axis=0))
    np.testing.assert_array_equal(pos, src.means * [-1, -1, 1])
    rot = accessor_values(doc, binary, attrs[K + "ROTATION"])
    np.testing.assert_allclose(np.linalg.norm(rot, axis=1), 1.0, atol=1e-6)  # unit quaternions
    assert accessor_values(doc, binary, attrs[K + "SCALE"]).min() >= 0
    op = accessor_values(doc, binary, attrs[K + "OPACITY"])
    assert op.min() >= 0 and op.max() <= 1
    np.testing.assert_array_equal(accessor_values(doc, binary, attrs[K + "SH_DEGREE_0_COEF_0"]), src.sh_dc[:, 0])
    # COLOR_0 is normalised unsigned bytes holding linear colour (sRGB decoded) and alpha.
    col = doc["accessors"][attrs["COLOR_0"]]
    assert (col["componentType"], col["type"], col["normalized"]) == (5121, "VEC4", True)
    rgb = np.clip(0.5 + SH_C0 * src.sh_dc[:, 0].astype(np.float64), 0, 1)
    lin = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(accessor_values(doc, binary, attrs["COLOR_0"])[:, :3] / 255, lin, atol=0.5 / 255 + 1e-9)
    np.testing.assert_array_equal(accessor_values(doc, binary, attrs["_tag"])[:, 0], src.extra["tag"])


def _validator():
    if shutil.which("node") is None:
        return None
    module = os.environ.get("MLX3D_GLTF_VALIDATOR") or str(REPO / ".tools" / "node_modules" / "gltf-validator")
    return module if os.path.isdir(module) else None


def test_khronos_validator_accepts_our_files(tmp_path):
    module = _validator()
    if module is None:
        pytest.skip("the Khronos glTF validator is not installed "
                    "(npm install --prefix .tools gltf-validator@2.0.0-dev.3.10, or MLX3D_GLTF_VALIDATOR=<its folder>)")
    src = real_splats()
    src.extra["tag"] = np.arange(src.count, dtype=np.uint8)
    write_splats(tmp_path / "v.glb", src)
    write_splats(tmp_path / "v.gltf", src)
    script = ("const v = require(process.argv[1]); const fs = require('fs');"
              "Promise.all(process.argv.slice(2).map(f => v.validateBytes(new Uint8Array(fs.readFileSync(f)))))"
              ".then(r => console.log(JSON.stringify(r.map(x => x.issues))),"
              "      e => { console.error(e); process.exit(2); });")
    out = subprocess.run(["node", "-e", script, module, str(tmp_path / "v.glb"), str(tmp_path / "v.gltf")],
                         capture_output=True, text=True, timeout=120, check=True).stdout
    for issues in json.loads(out):
        # The validator predates the extension: it reports its attribute names and the extension itself.
        left = [m for m in issues["messages"]
                if not (m["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE" and K in m["pointer"])
                and m["code"] != "UNSUPPORTED_EXTENSION"]
        assert left == [] and issues["numWarnings"] == 0, left


# --------------------------------------------------------------------------
# the peer
# --------------------------------------------------------------------------

def test_peer_file_reads_exactly():
    s = read_splats(PEER_GLB)
    ply = read_splat_ply(REAL_PLY, sh_degree=1)
    for key in ("means", "scales", "quats", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(s, key), getattr(ply, key), err_msg=key)
    assert_close_splats(s, ply, alpha=6e-8, what="peer")
    _check_activations(s, ply, "peer")


def test_peer_writes_what_we_write(tmp_path, splat_transform):  # noqa: F811
    src = adversarial_splats(span=1e4)
    write_splat_ply(tmp_path / "adv.ply", src)
    peer_path = splat_transform.convert(tmp_path / "adv.ply", tmp_path / "peer.glb")
    write_splats(tmp_path / "ours.glb", read_splat_ply(tmp_path / "adv.ply"))
    # The peer's file read by us: within our bounds of the PLY it read.
    peer = read_splats(peer_path)
    assert_close_splats(peer, src, scales=2e-6, **BOUNDS, what="peer file")
    _check_activations(peer, src, "peer file")
    # PLY -> .glb -> PLY: through the peer's writer and through ours, the same splats.
    ours = read_splats(tmp_path / "ours.glb")
    ours.extra.clear()
    assert_close_splats(ours, peer, scales=1e-6, **BOUNDS, what="peer vs ours")
    # Attribute by attribute, in the file's own (glTF) axes: the same values
    # (rotation: ours normalised; COLOR_0 differs: ours is sRGB-decoded as the
    # extension says, the peer's is not).
    pdoc, pbin = parse_glb(peer_path.read_bytes())
    odoc, obin = parse_glb((tmp_path / "ours.glb").read_bytes())
    pattr, oattr = pdoc["meshes"][0]["primitives"][0]["attributes"], odoc["meshes"][0]["primitives"][0]["attributes"]
    assert set(pattr) == {k for k in oattr if not k.startswith("_")}  # ours adds the PLY's normals as extras
    for name in pattr:
        if name == "COLOR_0":
            continue
        p, o = accessor_values(pdoc, pbin, pattr[name]), accessor_values(odoc, obin, oattr[name])
        if name == K + "ROTATION":
            p = p / np.linalg.norm(p, axis=1, keepdims=True) * np.sign(p[:, 3:] + 1e-30)
            o = o * np.sign(o[:, 3:] + 1e-30)
            np.testing.assert_allclose(o, p, atol=3e-7, err_msg=name)
        elif name == "POSITION":
            np.testing.assert_allclose(o, p, rtol=1e-6, atol=1e-6, err_msg=name)
        else:
            np.testing.assert_allclose(o, p, rtol=2.5e-7, atol=1e-7, err_msg=name)


# --------------------------------------------------------------------------
# bad files, detection, writer failures
# --------------------------------------------------------------------------

def _good(tmp_path) -> bytes:
    path = tmp_path / "good.glb"
    write_splats(path, real_splats(1))
    return path.read_bytes()


def test_truncated_files_are_named(tmp_path):
    data = _good(tmp_path)
    jlen = struct.unpack_from("<I", data, 12)[0]
    for cut, message in [(8, "GLB header"), (16, "truncated GLB file"), (20 + jlen // 2, "truncated GLB file"),
                         (len(data) - 100, "truncated GLB file")]:
        bad = tmp_path / f"cut{cut}.glb"
        bad.write_bytes(data[:cut])
        with pytest.raises(SplatFormatError, match=rf"cut{cut}\.glb.*{message}"):
            read_splats(bad)
    # A consistent header over a shortened BIN chunk: the buffer is too short.
    doc, binary = parse_glb(data)
    short = tmp_path / "short.glb"
    short.write_bytes(glb_bytes(doc, binary[:-400]))
    with pytest.raises(SplatFormatError, match=r"short\.glb.*truncated buffers\[0\].*byteLength"):
        read_splats(short)


def _mutated(tmp_path, name, change) -> str:
    doc, binary = parse_glb(_good(tmp_path))
    change(doc)
    path = tmp_path / name
    path.write_bytes(glb_bytes(doc, binary))
    return str(path)


def _attr(doc, name):
    return doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][name]]


@pytest.mark.parametrize("name, change, message", [
    ("mode", lambda d: d["meshes"][0]["primitives"][0].pop("mode"), "mode is 4.*POINTS"),
    ("noscale", lambda d: d["meshes"][0]["primitives"][0]["attributes"].pop(K + "SCALE"), "lacks.*SCALE"),
    ("partial", lambda d: d["meshes"][0]["primitives"][0]["attributes"].pop(K + "SH_DEGREE_1_COEF_2"),
     "SH degree 1 is partially defined"),
    ("ctype", lambda d: _attr(d, K + "OPACITY").update(componentType=5122), "stores signed short.*allows"),
    ("atype", lambda d: _attr(d, K + "SCALE").update(type="VEC4"), "is 'VEC4'.*must be VEC3"),
    ("count", lambda d: _attr(d, K + "SCALE").update(count=501), "needs 6012 bytes.*has 6000"),
    ("counts", lambda d: [_attr(d, n).update(count=400) for n in (K + "SCALE",)], "POSITION has 500.*scales.*400"),
    ("view", lambda d: _attr(d, "POSITION").update(bufferView=99), r"refers to bufferViews\[99\]"),
    ("required", lambda d: d.update(extensionsRequired=["KHR_gaussian_splatting_compression_spz_2"]),
     "requires.*compression_spz_2"),
    ("version", lambda d: d["asset"].update(version="1.0"), "asset.version is '1.0'"),
    ("nosplats", lambda d: d["meshes"][0]["primitives"][0].pop("extensions"), "no mesh primitive.*extension"),
    ("cycle", lambda d: d["nodes"][0].update(children=[0]), "own ancestor"),
    ("mirror", lambda d: d["nodes"][0].update(scale=[-1, 1, 1]), "mirrors"),
    ("datauri", lambda d: d["buffers"][0].update(uri="data:application/octet-stream,abc"), "not base64"),
    ("nobin", lambda d: d["buffers"][0].update(uri="missing.bin"), r"cannot read .*missing\.bin"),
])
def test_malformed_documents_are_named(tmp_path, name, change, message):
    path = _mutated(tmp_path, f"{name}.glb", change)
    with pytest.raises(SplatFormatError, match=rf"{name}\.glb.*{message}"):
        read_splats(path)


def test_bad_headers_are_named(tmp_path):
    data = bytearray(_good(tmp_path))
    for name, offset, value, message in [("magic", 0, b"glTX", "neither the GLB magic"),
                                         ("v1", 4, struct.pack("<I", 1), "GLB version 1"),
                                         ("chunk", 16, struct.pack("<I", 0x004E4942), "first GLB chunk")]:
        bad = bytearray(data)
        bad[offset:offset + 4] = value
        (tmp_path / f"{name}.glb").write_bytes(bad)
        with pytest.raises(SplatFormatError, match=rf"{name}\.glb.*{message}"):
            read_splats(tmp_path / f"{name}.glb", format="glb")
    (tmp_path / "json.gltf").write_text('{"asset": {"version": "2.0"}, ')
    with pytest.raises(SplatFormatError, match=r"json\.gltf.*not valid glTF JSON"):
        read_splats(tmp_path / "json.gltf")


def test_detection_by_content(tmp_path):
    data = _good(tmp_path)
    (tmp_path / "renamed.dat").write_bytes(data)
    assert read_splats(tmp_path / "renamed.dat").count == 500
    write_splats(tmp_path / "j.gltf", real_splats(0))
    shutil.copy(tmp_path / "j.gltf", tmp_path / "j.json")
    assert read_splats(tmp_path / "j.json").count == 500
    assert not sniff_gltf(b'{"version": 2, "asset": {"generator": "x"}, "count": 3}', "meta.json")
    assert not sniff_gltf(b"\0" * 64, "a.splat")
    assert sniff_gltf(b'{"buffers": []}', "a.gltf")


def test_writer_failures_leave_nothing(tmp_path):
    out = tmp_path / "keep.glb"
    out.write_bytes(b"old")
    src = real_splats()
    empty = SplatArrays(**{k: getattr(src, k)[:0] for k in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")})
    with pytest.raises(SplatFormatError, match=r"keep\.glb.*zero splats"):
        write_splats(out, empty)
    assert out.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.glb"]
