"""PlayCanvas compressed PLY: hand-built files decoded by the layout, round
trips within the module's bounds (mlx3d/io/compressed_ply.py), the peer both
ways (its files and ours, byte for byte), bad files, detection.

``tests/data/formats/opensplat_500.compressed.ply`` was written by the peer:
``splat-transform tests/data/formats/opensplat_500.ply
tests/data/formats/opensplat_500.compressed.ply`` (splat-transform 3.7.0).
"""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest

from format_cases import DATA, adversarial_splats, real_splats, splat_transform  # noqa: F401
from format_cases import assert_close_splats
from mlx3d.errors import NonFiniteError, SplatFormatError
from mlx3d.io import SplatArrays, detect_format, read_splat_ply, read_splats, write_splat_ply, write_splats
from mlx3d.io.codec import SH_C0, SNIFF_BYTES, sigmoid
from mlx3d.io.compressed_ply import morton_order, read_compressed_ply, sniff_compressed_ply

from core_marks import runs_no_kernel  # noqa: E402

pytestmark = runs_no_kernel  # file formats, datasets and packaging: no kernel of ours runs here

PEER_FILE = DATA / "opensplat_500.compressed.ply"

CHUNK_NAMES = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
               "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
COLOR_NAMES = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]

# The module's stated bounds that do not depend on the chunk (see _assert_within_bounds for the rest).
ROTATION = 0.005
ALPHA = 0.5 / 255 + 1e-6


def _ply(elements) -> bytes:
    """A little-endian PLY file: ``elements`` is ``[(name, count, [(type, property)], data bytes)]``."""
    lines = ["ply", "format binary_little_endian 1.0"]
    for name, count, props, _ in elements:
        lines.append(f"element {name} {count}")
        lines += [f"property {t} {p}" for t, p in props]
    lines.append("end_header\n")
    return "\n".join(lines).encode() + b"".join(e[3] for e in elements)


def _decode_one(chunk: dict, words, sh_bytes) -> dict:
    """One splat by the format description, in plain Python (no numpy, no module code)."""
    def unorm(v, bits):
        return (v & ((1 << bits) - 1)) / ((1 << bits) - 1)

    def lerp(lo, hi, t):
        return lo * (1 - t) + hi * t

    pos, rot, scale, color = words
    axes = [(21, 11), (11, 10), (0, 11)]
    out = {
        "means": [lerp(chunk[f"min_{a}"], chunk[f"max_{a}"], unorm(pos >> s, b)) for a, (s, b) in zip("xyz", axes)],
        "scales": [lerp(chunk[f"min_scale_{a}"], chunk[f"max_scale_{a}"], unorm(scale >> s, b))
                   for a, (s, b) in zip("xyz", axes)],
    }
    small = [(unorm(rot >> s, 10) - 0.5) * math.sqrt(2) for s in (20, 10, 0)]
    q = list(small)
    q.insert(rot >> 30, math.sqrt(max(0.0, 1 - sum(v * v for v in small))))
    out["quats"] = q
    rgb = [unorm(color >> s, 8) for s in (24, 16, 8)]
    if "min_r" in chunk:
        rgb = [lerp(chunk[f"min_{c}"], chunk[f"max_{c}"], t) for c, t in zip("rgb", rgb)]
    out["sh_dc"] = [(c - 0.5) / SH_C0 for c in rgb]
    out["alpha"] = unorm(color, 8)
    out["f_rest"] = [8 * ((0 if b == 0 else 1 if b == 255 else (b + 0.5) / 256) - 0.5) for b in sh_bytes]
    return out


def _check_decoded(got: SplatArrays, i: int, want: dict) -> None:
    np.testing.assert_allclose(got.means[i], want["means"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got.scales[i], want["scales"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got.quats[i], want["quats"], atol=1e-6)
    np.testing.assert_allclose(got.sh_dc[i, 0], want["sh_dc"], atol=1e-5)
    np.testing.assert_allclose(sigmoid(got.opacities[i]), want["alpha"], atol=1e-6)
    k1 = got.sh_rest.shape[1]
    # f_rest_{c*k1 + k} is sh_rest[:, k, c] (channel-major, as in PLY).
    np.testing.assert_allclose(got.sh_rest[i].T.reshape(-1), want["f_rest"], atol=1e-6)
    assert len(want["f_rest"]) == 3 * k1


@pytest.mark.parametrize("colour_bounds", [True, False])
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_hand_built_file_decodes_by_the_layout(tmp_path, colour_bounds, degree):
    # 300 splats: two chunks, splat 256 the first of the second.  Random words
    # and bytes; bounds chosen by hand; decoded by _decode_one for a few splats.
    rng = np.random.default_rng(degree)
    n = 300
    names = CHUNK_NAMES + (COLOR_NAMES if colour_bounds else [])
    chunks = np.array([[-1.0, 2.0, -30.0, 3.0, 2.5, 10.0, -9.0, -5.0, -2.0, 1.0, 0.0, -1.5,
                        -0.2, 0.0, 0.1, 1.3, 1.0, 0.9],
                       [5.0, 5.0, 5.0, 5.0, 6.0, 7.0, -20.0, -20.0, -4.0, 20.0, -3.0, -4.0,
                        0.5, 0.5, -1.0, 0.5, 0.75, 2.0]], np.float32)[:, :len(names)]
    words = rng.integers(0, 2**32, (n, 4), dtype=np.uint64).astype("<u4")
    words[0] = [0, 0, 0xFFFFFFFF, 0]              # all-zero and all-one codes, largest index 0
    words[1] = [0xFFFFFFFF, 3 << 30, 0, 0xFFFFFFFF]  # largest index 3, the rest at -1/sqrt(2)
    k3 = 3 * ((degree + 1) ** 2 - 1)
    sh = rng.integers(0, 256, (n, k3), dtype=np.uint8)
    if k3:
        sh[0, :3] = [0, 255, 128]
    elements = [("chunk", 2, [("float", nm) for nm in names], chunks.astype("<f4").tobytes()),
                ("vertex", n, [("uint", nm) for nm in PACKED], words.tobytes())]
    if k3:
        elements.append(("sh", n, [("uchar", f"f_rest_{i}") for i in range(k3)], sh.tobytes()))
    path = tmp_path / "hand.compressed.ply"
    path.write_bytes(_ply(elements))
    got = read_splats(path)
    assert got.count == n and got.sh_degree == degree
    for i in (0, 1, 2, 255, 256, 299):
        chunk = dict(zip(names, map(float, chunks[i // 256])))
        _check_decoded(got, i, _decode_one(chunk, [int(w) for w in words[i]], [int(b) for b in sh[i]]))
    np.testing.assert_array_equal(got.means[0], chunks[0, :3])  # code 0 -> the minimum
    np.testing.assert_array_equal(got.means[1], chunks[0, 3:6])  # all ones -> the maximum
    np.testing.assert_allclose(got.quats[1], [-0.5 ** 0.5] * 3 + [0.0], atol=1e-7)
    if k3:
        np.testing.assert_allclose(got.sh_rest[0, :3, 0], [-4.0, 4.0, 8 * (128.5 / 256 - 0.5)])  # f_rest_0..2


def test_writer_bytes_from_the_layout(tmp_path):
    # Two splats: bounds are their min/max, so every code sits at an end.
    s = SplatArrays(
        means=np.float32([[1.0, -2.0, 3.0], [2.0, 0.0, 3.0]]),
        scales=np.float32([[-30.0, 0.0, 1.0], [25.0, 0.5, 1.0]]),
        quats=np.float32([[2.0, 0.0, 0.0, 0.0], [0.0, 0.0, -3.0, 0.0]]),
        opacities=np.float32([0.0, 30.0]),
        sh_dc=np.float32([[[0.0, 1.0, -1.0]], [[0.5, 1.0, 2.0]]]),
        sh_rest=np.float32([[[0.1, -5.0, 4.0], [0.0, 0.0, 0.0], [-4.0, 3.99, -3.98]]] * 2))
    path = tmp_path / "two.compressed.ply"
    write_splats(path, s)
    data = path.read_bytes()
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:header_end].decode()
    assert header.startswith("ply\nformat binary_little_endian 1.0\nelement chunk 1\n")
    assert "element vertex 2\n" in header and "element sh 2\nproperty uchar f_rest_0\n" in header
    body = data[header_end:]
    assert len(body) == 18 * 4 + 2 * 16 + 2 * 9
    chunk = struct.unpack("<18f", body[:72])
    c = 0.5 + SH_C0 * np.float32([[0, 1, -1], [0.5, 1, 2]]).astype(np.float64)
    np.testing.assert_allclose(chunk, [1, -2, 3, 2, 0, 3, -20, 0, 1, 20, 0.5, 1,
                                       *c.min(axis=0), *c.max(axis=0)], rtol=1e-7)
    # Morton order puts splat 0 (smaller x, y) first.
    words = struct.unpack("<8I", body[72:104])
    assert words[0] == (0 << 21) | (0 << 11) | 0 and words[4] == (2047 << 21) | (1023 << 11) | 0
    # Identity: largest index 0, the others 0 -> floor(0.5 * 1023 + 0.5) = 512.
    assert words[1] == (0 << 30) | (512 << 20) | (512 << 10) | 512
    # -y: largest index 2 made positive.
    assert words[5] == (2 << 30) | (512 << 20) | (512 << 10) | 512
    # Scales: -30 clamps to the -20 bound, 25 to 20; z's range is empty -> 0.
    assert words[2] == 0 and words[6] == (2047 << 21) | (1023 << 11) | 0
    # Colour over the chunk's colour range: every channel at an end; alpha 0.5 -> 128, 1 -> 255.
    assert words[3] == (0 << 24) | (0 << 16) | (0 << 8) | 128
    assert words[7] == (255 << 24) | (0 << 16) | (255 << 8) | 255
    # SH byte trunc(256 * (v / 8 + 0.5)) clamped, channel-major: f_rest_{c*3 + k} = sh_rest[k, c].
    f_rest = list(body[104:113])
    assert f_rest == [131, 128, 0, 0, 128, 255, 255, 128, 0]


def test_big_endian_and_empty_files(tmp_path):
    # The committed peer file rewritten big-endian reads the same.
    data = PEER_FILE.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    swapped = b"".join([
        np.frombuffer(body[:2 * 72], "<f4").astype(">f4").tobytes(),
        np.frombuffer(body[2 * 72:2 * 72 + 500 * 16], "<u4").astype(">u4").tobytes(),
        body[2 * 72 + 500 * 16:]])
    path = tmp_path / "be.compressed.ply"
    path.write_bytes(header.replace(b"binary_little_endian", b"binary_big_endian") + b"end_header\n" + swapped)
    assert_close_splats(read_splats(path), read_splats(PEER_FILE), what="big-endian")
    # No splats: no chunk rows.
    empty = tmp_path / "empty.compressed.ply"
    write_splats(empty, SplatArrays(
        means=np.zeros((0, 3), np.float32), scales=np.zeros((0, 3), np.float32), quats=np.zeros((0, 4), np.float32),
        opacities=np.zeros(0, np.float32), sh_dc=np.zeros((0, 1, 3), np.float32),
        sh_rest=np.zeros((0, 3, 3), np.float32)))
    assert b"element chunk 0\n" in empty.read_bytes()
    got = read_compressed_ply(empty)
    assert got.count == 0 and got.sh_degree == 1


def _representable(s: SplatArrays) -> SplatArrays:
    """``s`` in the writer's order with log scales clamped to [-20, 20] and SH to [-4, 4]."""
    o = morton_order(s.means)
    return SplatArrays(
        means=s.means[o], scales=np.clip(s.scales[o], -20, 20), quats=s.quats[o], opacities=s.opacities[o],
        sh_dc=s.sh_dc[o], sh_rest=np.clip(s.sh_rest[o], -4, 4))


def _chunk_range(values: np.ndarray) -> np.ndarray:
    """Per splat, the range ``hi - lo`` of its chunk (256 consecutive splats), ``(N, D)``."""
    v = values.reshape(len(values), -1).astype(np.float64)
    first = np.arange(0, len(v), 256)
    span = np.maximum.reduceat(v, first) - np.minimum.reduceat(v, first)
    return span[np.arange(len(v)) // 256]


def _assert_within_bounds(got: SplatArrays, want: SplatArrays, what: str) -> None:
    """The module's per-splat bounds: half a step of the chunk's range (+ float32 rounding)."""
    assert_close_splats(got, want, means=np.inf, scales=np.inf, rotation=ROTATION, alpha=ALPHA,
                        sh_dc=np.inf, sh_rest=1 / 32 + 1e-6, what=what)
    f32 = 2.0 ** -24

    def check(name, a, b, bound):
        err = np.abs(np.asarray(a, np.float64).reshape(bound.shape) - np.asarray(b, np.float64).reshape(bound.shape))
        worst = np.unravel_index(np.argmax(err - bound), err.shape)
        assert (err <= bound).all(), f"{what}: {name} {worst} off by {err[worst]:.3g} > {bound[worst]:.3g}"

    steps = np.array([2047.0, 1023.0, 2047.0])
    for name in ("means", "scales"):
        w = getattr(want, name).astype(np.float64)
        check(name, getattr(got, name), w, 0.5 * _chunk_range(w) / steps * (1 + 1e-6) + f32 * np.abs(w) + 1e-12)
    colour = (0.5 + SH_C0 * want.sh_dc.reshape(-1, 3).astype(np.float64)).astype(np.float32).astype(np.float64)
    dc = want.sh_dc.reshape(-1, 3).astype(np.float64)
    check("sh_dc", got.sh_dc, dc,
          (0.5 * _chunk_range(colour) / 255 * (1 + 1e-6) + f32 * np.abs(colour)) / SH_C0 + f32 * np.abs(dc) + 1e-12)
    rest = want.sh_rest.astype(np.float64)
    check("sh_rest", got.sh_rest, rest, np.where(np.abs(rest) <= 4 - 1 / 32, 1 / 64, 1 / 32) + 1e-6)


@pytest.mark.parametrize("case", ["real", "adversarial", "far", "degree1"])
def test_round_trip_within_bounds(tmp_path, case):
    src = {"real": real_splats, "adversarial": adversarial_splats,
           "far": lambda: adversarial_splats(n=700, span=1e4, seed=2),
           "degree1": lambda: adversarial_splats(n=300, degree=1, seed=3)}[case]()
    path = tmp_path / "a.compressed.ply"
    write_splats(path, src)
    got = read_splats(path)
    _assert_within_bounds(got, _representable(src), case)


def test_clamped_values(tmp_path):
    src = adversarial_splats(n=40, seed=4)
    src.scales[:5] = [[-25, 22, 0]] * 5
    src.sh_rest[:5] = 5.0
    src.sh_rest[5:10] = -4.5
    path = tmp_path / "c.compressed.ply"
    write_splats(path, src)
    got = read_splats(path)
    _assert_within_bounds(got, _representable(src), "clamped")
    assert got.scales.min() == -20 and got.scales.max() == 20
    assert got.sh_rest.max() == 4 and got.sh_rest.min() == -4


def test_peer_file_is_read_within_bounds_and_our_writer_makes_its_bytes(tmp_path):
    # The committed peer file: the peer's Morton order is ours, so its values
    # match the source in that order, and our writer reproduces its bytes.
    src = real_splats()
    got = read_splats(PEER_FILE)
    assert got.comments == ["Generated by splat-transform 3.7.0"]
    _assert_within_bounds(got, _representable(src), "peer file")
    ours = tmp_path / "ours.compressed.ply"
    write_splats(ours, src)
    peer, mine = PEER_FILE.read_bytes(), ours.read_bytes()
    assert mine == peer.replace(b"comment Generated by splat-transform 3.7.0\n", b"")


def test_peer_writes_what_we_write(tmp_path, splat_transform):  # noqa: F811
    src = adversarial_splats(n=600, seed=6)
    ply = tmp_path / "adv.ply"
    write_splat_ply(ply, src)
    peer = splat_transform.convert(ply, tmp_path / "peer.compressed.ply")
    _assert_within_bounds(read_splats(peer), _representable(src), "peer")
    ours = tmp_path / "ours.compressed.ply"
    write_splats(ours, src)
    body = peer.read_bytes().split(b"end_header\n", 1)
    assert ours.read_bytes() == body[0].replace(b"comment Generated by splat-transform 3.7.0\n", b"") \
        + b"end_header\n" + body[1]


def _peer_ply(splat_transform, src_path, out_path) -> SplatArrays:  # noqa: F811
    """The peer's PLY of ``src_path``, its count and SH degree checked against ``--info json``."""
    info = splat_transform.run(str(src_path), "--info", "json", "null")
    meta = json.loads(info[info.index("{"):info.rindex("}") + 1])
    back = read_splat_ply(splat_transform.convert(src_path, out_path), nonfinite="keep")
    assert (meta["numGaussians"], meta["shBands"]) == (back.count, back.sh_degree)
    return back


# The peer writes alpha 0 and 1 as infinite opacity logits: its PLYs are read with nonfinite="keep".
PEER_INFINITE_LOGITS = pytest.mark.filterwarnings("ignore:.*NaN or Inf values.*'opacity':UserWarning")


@PEER_INFINITE_LOGITS
def test_peer_reads_our_files(tmp_path, splat_transform):  # noqa: F811
    # The peer decodes in float64 and rounds once, as we do: the same float32
    # values but for opacities at alpha 0 or 1 (infinite logits there).
    for name, src in [("real", real_splats()), ("adversarial", adversarial_splats(seed=7))]:
        ours = tmp_path / f"{name}.compressed.ply"
        write_splats(ours, src)
        mine = read_splats(ours)
        peer = _peer_ply(splat_transform, ours, tmp_path / f"{name}.ply")
        assert_close_splats(peer, mine, rotation=1e-6, alpha=1e-6, what=name)
        # PLY -> compressed -> PLY through the peer matches ours within bounds.
        ply = tmp_path / f"{name}.src.ply"
        write_splat_ply(ply, src)
        via_peer = splat_transform.convert(
            splat_transform.convert(ply, tmp_path / f"{name}.peer.compressed.ply"), tmp_path / f"{name}.peer.ply")
        via_us = tmp_path / f"{name}.us.ply"
        write_splat_ply(via_us, mine)
        assert_close_splats(read_splat_ply(via_peer, nonfinite="keep"), read_splat_ply(via_us),
                            rotation=1e-6, alpha=1e-6, what=name)


@PEER_INFINITE_LOGITS
def test_peer_reads_files_without_colour_bounds_or_sh(tmp_path, splat_transform):  # noqa: F811
    # The older layout: 12 chunk properties, colour over [0, 1], no sh element.
    rng = np.random.default_rng(8)
    chunks = np.float32([[-1, -2, -3, 1, 2, 3, -5, -4, -3, 0, 1, 2]])
    words = rng.integers(0, 2**32, (100, 4), dtype=np.uint64).astype("<u4")
    path = tmp_path / "old.compressed.ply"
    path.write_bytes(_ply([("chunk", 1, [("float", nm) for nm in CHUNK_NAMES], chunks.tobytes()),
                           ("vertex", 100, [("uint", nm) for nm in PACKED], words.tobytes())]))
    mine = read_splats(path)
    assert mine.sh_degree == 0
    np.testing.assert_allclose(0.5 + SH_C0 * mine.sh_dc[:, 0, 0], (words[:, 3] >> 24) / 255, atol=1e-6)
    peer = _peer_ply(splat_transform, path, tmp_path / "old.ply")
    assert_close_splats(peer, mine, rotation=1e-6, alpha=1e-6, what="old layout")


def _valid_file(tmp_path) -> bytes:
    path = tmp_path / "valid.compressed.ply"
    write_splats(path, real_splats())
    return path.read_bytes()


def test_truncated_files_are_named(tmp_path):
    data = _valid_file(tmp_path)
    start = data.index(b"end_header\n") + len(b"end_header\n")
    cuts = {
        "in the header": (data.index(b"element vertex"), r"no 'end_header'"),
        "in the chunks": (start + 40, r"truncated compressed PLY: element 'chunk' \(2 rows of 72 bytes\)"),
        "in the vertices": (start + 72 * 2 + 16 * 300, r"element 'vertex' \(500 rows of 16 bytes\) needs 8000 bytes"),
        "in the SH": (len(data) - 1, r"element 'sh' \(500 rows of 45 bytes\) needs 22500 bytes .* 22499 remain"),
    }
    for where, (cut, message) in cuts.items():
        path = tmp_path / f"cut {where}.compressed.ply"
        path.write_bytes(data[:cut])
        with pytest.raises(SplatFormatError, match=rf"cut {where}\.compressed\.ply: .*{message}"):
            read_splats(path)


@pytest.mark.parametrize("change, message", [
    ((b"element chunk 2\n", b"element other 2\n"), r"no 'chunk' element"),
    ((b"element chunk 2\n", b"element chunk 3\n"), r"500 splats need 2 chunk rows of 256 splats; the file declares 3"),
    ((b"element sh 500\n", b"element sh 499\n"), r"element 'sh' has 499 rows but 'vertex' has 500"),
    ((b"property uint packed_rotation\n", b"property uint packed_rot\n"), r"lacks the packed .* packed_rotation"),
    ((b"property uint packed_scale\n", b"property float packed_scale\n"), r"packed_scale \(f4\)"),
    ((b"property float max_r\n", b"property float max_red\n"), r"lacks the colour bounds .* max_r"),
    ((b"property uchar f_rest_44\n", b""), r"'sh' has 44 properties; expected 9, 24 or 45"),
    ((b"property uchar f_rest_7\n", b"property uchar f_rest_x\n"), r"lacks the SH .* f_rest_7"),
    ((b"binary_little_endian", b"ascii"), r"must be binary; this one is ascii"),
    ((b"format binary_little_endian 1.0", b"format binary_little_endian 2.0"), r"unsupported PLY version"),
])
def test_malformed_headers_are_named(tmp_path, change, message):
    path = tmp_path / "bad.compressed.ply"
    data = _valid_file(tmp_path)
    assert change[0] in data
    path.write_bytes(data.replace(change[0], change[1], 1))
    with pytest.raises(SplatFormatError, match=rf"bad\.compressed\.ply: .*{message}"):
        read_splats(path)


def test_failed_write_leaves_no_file(tmp_path):
    out = tmp_path / "keep.compressed.ply"
    out.write_bytes(b"old")
    bad = real_splats()
    bad.scales[7, 2] = np.inf
    with pytest.raises(NonFiniteError, match=r"scales.*splat 7"):
        write_splats(out, bad)
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.compressed.ply"]


def test_detection_by_content(tmp_path):
    src = real_splats(1)
    for name in ("scene.ply", "scene.bin"):
        path = tmp_path / name
        write_splats(path, src, format="compressed-ply")
        assert detect_format(path).name == "compressed-ply"
        assert read_splats(path).count == src.count
    # A plain 3DGS PLY under the compressed extension is read as plain PLY.
    plain = tmp_path / "plain.compressed.ply"
    write_splat_ply(plain, src)
    assert detect_format(plain).name == "ply"
    assert read_splats(plain).sh_degree == 1
    head = (DATA / "opensplat_500.ply").read_bytes()[:SNIFF_BYTES]
    assert not sniff_compressed_ply(head, "x.ply")
    assert sniff_compressed_ply(PEER_FILE.read_bytes()[:SNIFF_BYTES], "x")
    # Either marker suffices, so a file missing its chunk element still reaches our reader.
    no_chunk = _ply([("vertex", 0, [("uint", nm) for nm in PACKED], b"")])
    assert sniff_compressed_ply(no_chunk, "x")
    assert not sniff_compressed_ply(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n"
                                    b"element chunk 1\n", "x")
