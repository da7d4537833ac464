"""Niantic ``.spz``: files of every version built from the specification,
round trips within the stated bounds (mlx3d/io/spz.py), the peer both ways
(its bytes equal ours), coordinate-system extensions, bad files.

``tests/data/formats/opensplat_500_v4.spz`` and ``opensplat_500_v3.spz``
were written by splat-transform 3.7.0 from ``opensplat_500.ply``::

    splat-transform opensplat_500.ply opensplat_500_v4.spz
    splat-transform opensplat_500.ply opensplat_500_v3.spz --spz-version 3
"""

from __future__ import annotations

import gzip
import json
import re
import struct
import sys

import numpy as np
import pytest
import zstandard

from format_cases import DATA, REAL_PLY, adversarial_splats, assert_close_splats, real_splats, rotations
from format_cases import splat_transform  # noqa: F401
from mlx3d.errors import SplatFormatError
from mlx3d.io import SplatArrays, detect_format, read_splat_ply, read_splats, write_splat_ply, write_splats
from mlx3d.io.codec import sigmoid
from mlx3d.io.spz import frame_matrix, read_spz, sh_transform, write_spz

from core_marks import runs_no_kernel  # noqa: E402

pytestmark = runs_no_kernel  # file formats, datasets and packaging: no kernel of ours runs here

PEER_V4 = DATA / "opensplat_500_v4.spz"
PEER_V3 = DATA / "opensplat_500_v3.spz"

# The module's stated bounds, plus float32 rounding where a value is computed in float32.
BOUNDS = dict(means=0.5 / 4096, scales=1 / 32 + 1e-6, rotation=0.004, alpha=0.5 / 255 + 1e-6,
              sh_dc=0.5 / 255 / 0.15 + 1e-6, sh_rest=8.5 / 128)
SH1_BOUND = 4.5 / 128
# What two readers of the same bytes may differ by (float32 vs float64 decoding).
SAME_BYTES = dict(means=0.0, scales=0.0, rotation=1e-6, alpha=1e-6, sh_dc=1e-6, sh_rest=0.0)


def _representable(s: SplatArrays) -> SplatArrays:
    """``s`` clamped to what SPZ can hold (log scales, colours, SH)."""
    return SplatArrays(
        means=s.means, quats=s.quats, opacities=s.opacities,
        scales=np.clip(s.scales, -10.0, 255 / 16 - 10.0),
        sh_dc=np.clip(s.sh_dc, -127.5 / 38.25, 127.5 / 38.25),
        sh_rest=np.clip(s.sh_rest, -1.0, 127 / 128))


def _assert_within_bounds(got: SplatArrays, src: SplatArrays, what: str, rotation=BOUNDS["rotation"]):
    want = _representable(src)
    assert_close_splats(got, want, **{**BOUNDS, "rotation": rotation}, what=what)
    err = np.abs(got.sh_rest[:, :3].astype(np.float64) - want.sh_rest[:, :3]).max(initial=0.0)
    assert err <= SH1_BOUND, f"{what}: degree-1 SH differ by {err:.3g}"


# --------------------------------------------------------------------------
# Files built from the specification
# --------------------------------------------------------------------------

def _int24(values) -> bytes:
    return b"".join(struct.pack("<i", v)[:3] for v in values)


# Two splats, SH degree 1, field by field (the blocks every version shares).
POSITIONS = _int24([6144, -9216, 1, -(1 << 23), (1 << 23) - 1, 0])    # fixed point, 12 fractional bits
ALPHAS = bytes([191, 0])
COLOURS = bytes([255, 128, 0, 64, 192, 127])
SCALES = bytes([0, 160, 255, 16, 32, 48])
SH = bytes([0, 64, 128, 192, 255, 136, 120, 8, 248, 128, 128, 128, 1, 2, 3, 250, 251, 252])
# Smallest three: splat 0 stores w as largest (index 3), x = +434; splat 1 stores x
# as largest (index 0), y = -511, z = 0, w = +100.
ROT3 = struct.pack("<2I", 3 << 30 | 434 << 20, 0 << 30 | (1 << 9 | 511) << 20 | 0 << 10 | 100)
ROT2 = bytes([128, 128, 255, 0, 255, 127])                             # x, y, z as 127.5 q + 127.5


def _expected(rot: str) -> SplatArrays:
    """The two splats above, decoded with the specification's formulas."""
    s = 2 ** -12
    means = np.array([[6144, -9216, 1], [-(1 << 23), (1 << 23) - 1, 0]]) * s
    if rot == "smallest three":
        x0 = 434 / 511 * np.sqrt(0.5)
        y1, w1 = -np.sqrt(0.5), 100 / 511 * np.sqrt(0.5)
        quats = [[np.sqrt(1 - x0 ** 2), x0, 0, 0], [w1, np.sqrt(1 - y1 ** 2 - w1 ** 2), y1, 0]]
    else:
        xyz = np.frombuffer(ROT2, np.uint8).reshape(2, 3) / 127.5 - 1
        quats = np.concatenate([np.sqrt(np.maximum(0, 1 - (xyz ** 2).sum(1)))[:, None], xyz], 1)
    alpha = np.frombuffer(ALPHAS, np.uint8) / 255
    return SplatArrays(
        means=means.astype(np.float32),
        scales=(np.frombuffer(SCALES, np.uint8).reshape(2, 3) / 16 - 10).astype(np.float32),
        quats=np.array(quats, np.float32),
        opacities=np.log(np.clip(alpha, 1e-6, 1 - 1e-6) / (1 - np.clip(alpha, 1e-6, 1 - 1e-6))).astype(np.float32),
        sh_dc=((np.frombuffer(COLOURS, np.uint8) / 255 - 0.5) / 0.15).reshape(2, 1, 3).astype(np.float32),
        sh_rest=((np.frombuffer(SH, np.uint8) - 128.0) / 128).reshape(2, 3, 3).astype(np.float32))


def _legacy(version=3, n=2, degree=1, flags=0, blocks=None, after=b"", fractional_bits=12) -> bytes:
    """A gzip-compressed version 1-3 file: 16-byte header, blocks, ``after``."""
    if blocks is None:
        blocks = [POSITIONS, ALPHAS, COLOURS, SCALES, ROT3 if version >= 3 else ROT2, SH]
    header = struct.pack("<4sIIBBBB", b"NGSP", version, n, degree, fractional_bits, flags, 0)
    return gzip.compress(header + b"".join(blocks) + after)


def _v4(n=2, degree=1, flags=0, blocks=None, ext=b"", version=4, fractional_bits=12, count=None) -> bytes:
    """A version 4 file: 32-byte header, extensions, TOC, one ZSTD stream per non-empty block."""
    if blocks is None:
        blocks = [POSITIONS, ALPHAS, COLOURS, SCALES, ROT3, SH]
    blocks = [b for b in blocks if b]
    packed = [zstandard.ZstdCompressor().compress(b) for b in blocks]
    header = struct.pack("<4sIIBBBBI12x", b"NGSP", version, n, degree, fractional_bits, flags,
                         len(blocks) if count is None else count, 32 + len(ext))
    toc = b"".join(struct.pack("<QQ", len(p), len(b)) for p, b in zip(packed, blocks))
    return header + ext + toc + b"".join(packed)


@pytest.mark.parametrize("version", [2, 3, 4])
def test_files_built_from_the_specification(tmp_path, version):
    path = tmp_path / f"v{version}.spz"
    path.write_bytes(_v4() if version == 4 else _legacy(version))
    got = read_splats(path)
    want = _expected("smallest three" if version >= 3 else "first three")
    assert_close_splats(got, want, rotation=1e-6, alpha=1e-7, sh_dc=1e-6, what=f"v{version}")
    np.testing.assert_array_equal(got.means, want.means)
    np.testing.assert_allclose(got.quats, want.quats, atol=1e-7)
    np.testing.assert_array_equal(got.sh_rest, want.sh_rest)
    assert got.comments == []


def test_version_1_float16_positions_and_an_uncompressed_stream(tmp_path):
    pos = struct.pack("<6e", 1.5, -2.25, 0.125, -1000.0, 0.0, 65504.0)
    v1 = tmp_path / "v1.spz"
    v1.write_bytes(_legacy(1, blocks=[pos, ALPHAS, COLOURS, SCALES, ROT2, SH]))
    got = read_splats(v1)
    np.testing.assert_array_equal(got.means, [[1.5, -2.25, 0.125], [-1000.0, 0.0, 65504.0]])
    assert_close_splats(got, SplatArrays(**{**vars(_expected("first three")), "means": got.means}),
                        rotation=1e-6, alpha=1e-7, sh_dc=1e-6, what="v1")
    # A version 3 stream stored without gzip (splat-transform reads these too).
    plain = tmp_path / "plain.spz"
    plain.write_bytes(gzip.decompress(_legacy(3)))
    assert_close_splats(read_splats(plain), _expected("smallest three"), rotation=1e-6, alpha=1e-7,
                        sh_dc=1e-6, what="plain")


def test_degree_0_zero_splats_and_the_antialiased_flag(tmp_path):
    blocks = [POSITIONS, ALPHAS, COLOURS, SCALES, ROT3, b""]
    for name, data in [("v4.spz", _v4(degree=0, blocks=blocks, flags=1)),
                       ("v3.spz", _legacy(3, degree=0, blocks=blocks, flags=1))]:
        (tmp_path / name).write_bytes(data)
        got = read_splats(tmp_path / name)
        assert got.sh_degree == 0 and got.count == 2
        assert got.comments == ["antialiased 1"]
    empty = SplatArrays(means=np.zeros((0, 3), np.float32), scales=np.zeros((0, 3), np.float32),
                        quats=np.zeros((0, 4), np.float32), opacities=np.zeros(0, np.float32),
                        sh_dc=np.zeros((0, 1, 3), np.float32), sh_rest=np.zeros((0, 0, 3), np.float32))
    for version in (3, 4):
        write_spz(tmp_path / "empty.spz", empty, version=version)
        assert read_spz(tmp_path / "empty.spz").count == 0


def test_the_antialiased_flag_follows_the_comments(tmp_path):
    src = real_splats(1)
    cases = [([], 0), (["antialiased 1"], 1), (["SplatRenderMode: mip"], 1),
             (["Antialiased 1", "splatrendermode: default"], 0), (["antialiased 0", "x", "antialiased 1"], 1)]
    for comments, flag in cases:
        src.comments = comments
        for version in (3, 4):
            write_spz(tmp_path / "a.spz", src, version=version)
            data = (tmp_path / "a.spz").read_bytes()
            assert (gzip.decompress(data) if version == 3 else data)[14] == flag, (comments, version)
            assert read_splats(tmp_path / "a.spz").comments == ["antialiased 1"] * flag


# --------------------------------------------------------------------------
# Round trips through us
# --------------------------------------------------------------------------

@pytest.mark.parametrize("version", [4, 3, 2])
@pytest.mark.parametrize("case", ["real", "adversarial"])
def test_round_trip_within_bounds(tmp_path, case, version):
    src = real_splats() if case == "real" else adversarial_splats(n=2000, span=2000.0)
    path = tmp_path / "a.spz"
    write_spz(path, src, version=version)
    got = read_splats(path)
    _assert_within_bounds(got, src, f"{case} v{version}", rotation=0.004 if version >= 3 else 0.2)
    # Saving what was read again changes no position, alpha, colour, scale or SH
    # byte; a rotation moves by less than one step (a near-tie can change which
    # component is dropped, and a zero keeps its sign bit).
    again = tmp_path / "b.spz"
    write_spz(again, got, version=version)
    back = read_splats(again)
    assert_close_splats(back, got, rotation=0.5 / 511 * 4 if version >= 3 else 0.2, what="again")


def test_measured_rotation_bounds(tmp_path):
    # 200k random rotations (half of them near w = 0) through each encoding: the bounds the module states.
    rng = np.random.default_rng(3)
    q = rng.normal(size=(200_000, 4))
    q[::2, 0] *= 1e-3
    n = len(q)
    s = SplatArrays(means=np.zeros((n, 3), np.float32), scales=np.zeros((n, 3), np.float32),
                    quats=q.astype(np.float32), opacities=np.zeros(n, np.float32),
                    sh_dc=np.zeros((n, 1, 3), np.float32), sh_rest=np.zeros((n, 0, 3), np.float32))
    for version, bound in ((4, 0.004), (2, 0.2)):
        write_spz(tmp_path / "r.spz", s, version=version, fsync=False)
        err = np.abs(rotations(read_spz(tmp_path / "r.spz").quats) - rotations(q)).max()
        assert err <= bound, (version, err)


# --------------------------------------------------------------------------
# The peer
# --------------------------------------------------------------------------

def test_our_bytes_equal_the_peers_files(tmp_path):
    # Same input, same quantisation and compression: identical files (v3 and v4).
    src = real_splats()
    write_splats(tmp_path / "ours.spz", src)
    write_spz(tmp_path / "ours3.spz", src, version=3)
    assert (tmp_path / "ours.spz").read_bytes() == PEER_V4.read_bytes()
    assert (tmp_path / "ours3.spz").read_bytes() == PEER_V3.read_bytes()


def test_peer_files_are_read_within_bounds():
    for path in (PEER_V4, PEER_V3):
        got = read_splats(path)
        _assert_within_bounds(got, real_splats(), path.name)
        assert got.comments == []


def test_peer_writes_our_bytes_for_adversarial_splats(tmp_path, splat_transform):  # noqa: F811
    src = adversarial_splats(n=1000, span=2000.0)
    write_splat_ply(tmp_path / "adv.ply", src)
    for version in (4, 3):
        peer = splat_transform.convert(tmp_path / "adv.ply", tmp_path / f"peer{version}.spz",
                                       "--spz-version", str(version))
        write_spz(tmp_path / f"ours{version}.spz", src, version=version)
        assert peer.read_bytes() == (tmp_path / f"ours{version}.spz").read_bytes(), version
        _assert_within_bounds(read_splats(peer), src, f"peer v{version}")


@pytest.mark.parametrize("version", [4, 3])
def test_peer_reads_our_files(tmp_path, splat_transform, version):  # noqa: F811
    for case, src in (("real", real_splats()), ("adversarial", adversarial_splats(span=2000.0))):
        ours = tmp_path / f"{case}.spz"
        write_spz(ours, src, version=version)
        back = read_splat_ply(splat_transform.convert(ours, tmp_path / f"{case}.ply"))
        assert_close_splats(back, read_splats(ours), **SAME_BYTES, what=f"peer reading {case} v{version}")


def test_ply_spz_ply_through_us_and_through_the_peer(tmp_path, splat_transform):  # noqa: F811
    peer_spz = splat_transform.convert(REAL_PLY, tmp_path / "peer.spz")
    peer_ply = read_splat_ply(splat_transform.convert(peer_spz, tmp_path / "peer.ply"))
    write_splats(tmp_path / "ours.spz", real_splats())
    write_splats(tmp_path / "ours.ply", read_splats(tmp_path / "ours.spz"))
    ours = read_splat_ply(tmp_path / "ours.ply")
    assert_close_splats(ours, peer_ply, **SAME_BYTES, what="PLY -> SPZ -> PLY")


def test_antialiased_flag_with_the_peer(tmp_path, splat_transform):  # noqa: F811
    src = real_splats(1)
    write_splat_ply(tmp_path / "aa.ply", src, comments=["antialiased 1"])   # Postshot's comment
    assert read_splats(splat_transform.convert(tmp_path / "aa.ply", tmp_path / "peer.spz")).comments == [
        "antialiased 1"]
    src.comments = read_splat_ply(tmp_path / "aa.ply").comments
    write_splats(tmp_path / "ours.spz", src)
    info = splat_transform.run(str(tmp_path / "ours.spz"), "--info", "json", "null")
    assert json.loads(re.search(r"^\{.*^\}", info, re.S | re.M).group(0))["model"] == "antialiased"


# --------------------------------------------------------------------------
# Coordinate systems (Adobe's extension 0xADBE0003)
# --------------------------------------------------------------------------

def _record(kind: int, payload: bytes) -> bytes:
    return struct.pack("<II", kind, len(payload)) + payload


def _frame_record(value: int) -> bytes:
    return _record(0xADBE0003, struct.pack("<I", value))


def _stored(tmp_path, ext: bytes, version: int = 4) -> tuple[SplatArrays, SplatArrays]:
    """Splats as stored (no extension) and as read with extension records ``ext``."""
    src = real_splats()
    write_spz(tmp_path / "plain.spz", src, version=version)
    data = (tmp_path / "plain.spz").read_bytes()
    if version == 4:
        toc = struct.unpack_from("<I", data, 16)[0]
        data = (data[:14] + bytes([data[14] | 2]) + data[15:16] + struct.pack("<I", toc + len(ext))
                + data[20:32] + ext + data[32:])
    else:
        raw = gzip.decompress(data)
        data = gzip.compress(raw[:14] + bytes([raw[14] | 2]) + raw[15:] + ext)
    (tmp_path / "ext.spz").write_bytes(data)
    return read_splats(tmp_path / "plain.spz"), read_splats(tmp_path / "ext.spz")


@pytest.mark.parametrize("version", [4, 3])
def test_rub_files_are_turned_to_ply_axes(tmp_path, version):
    # An unknown record (skipped by its length), then the frame RUB (4).
    stored, got = _stored(tmp_path, _record(0x12340001, b"\1\2\3\4\5") + _frame_record(4), version)
    np.testing.assert_array_equal(got.means, stored.means * [1, -1, -1])
    # Niantic's flips for x, y, z = +1, -1, -1: quaternion x, y, z by y*z, x*z, x*y, and
    # per SH coefficient the signs of its table (degree 1-3).
    np.testing.assert_array_equal(got.quats, stored.quats * [1, 1, -1, -1])
    signs = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1])
    np.testing.assert_allclose(got.sh_rest, stored.sh_rest * signs[:, None], atol=1e-6)
    for field in ("scales", "opacities", "sh_dc"):
        np.testing.assert_array_equal(getattr(got, field), getattr(stored, field))


def test_a_z_up_frame_is_turned_to_ply_axes(tmp_path):
    stored, got = _stored(tmp_path, _frame_record(12))  # RFU: x right, y forward, z up
    m = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    np.testing.assert_array_equal(frame_matrix("RFU"), m)
    np.testing.assert_allclose(got.means, stored.means @ m.T, atol=1e-6)
    # Covariances follow the positions.
    cov = lambda s: np.einsum("nij,nj,nkj->nik", rotations(s.quats), np.exp(2.0 * s.scales), rotations(s.quats))
    np.testing.assert_allclose(cov(got), m @ cov(stored) @ m.T, atol=1e-6 * cov(stored).max())
    # Rotations as Niantic composes them: flip to RUB-as-RDF, then a quarter turn about x.
    flip, turn = np.diag([1.0, -1.0, -1.0]), np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    np.testing.assert_allclose(rotations(got.quats), turn @ flip @ rotations(stored.quats) @ flip, atol=1e-6)
    # Degree-1 SH by hand: Y1(d) = C1 (-y, z, -x), and Y1(m d) . c' == Y1(d) . c gives c' = (c1, -c0, c2).
    c = stored.sh_rest[:, :3]
    np.testing.assert_allclose(got.sh_rest[:, :3], np.stack([c[:, 1], -c[:, 0], c[:, 2]], 1), atol=1e-6)


def test_sh_transforms_keep_the_colour_seen_from_each_direction():
    sh = pytest.importorskip("mlx3d.splatting.sh", reason="mlx3d.splatting needs MLX")
    rng = np.random.default_rng(0)
    coeffs = rng.normal(size=(16, 3))
    dirs = rng.normal(size=(64, 3))
    for frame in ("RUB", "LDB", "RDB", "RFU", "LBD", "RBU"):
        m = frame_matrix(frame)
        moved = np.concatenate([coeffs[:1], sh_transform(m, 3) @ coeffs[1:]])
        # colour(M d) of the converted coefficients == colour(d) of the stored ones
        np.testing.assert_allclose(sh.eval_sh(3, moved[None], dirs @ m.T), sh.eval_sh(3, coeffs[None], dirs), atol=1e-9,
                                   err_msg=frame)


def test_unspecified_and_unknown_frames_read_as_stored(tmp_path):
    stored, got = _stored(tmp_path, _frame_record(0))
    np.testing.assert_array_equal(got.means, stored.means)
    with pytest.warns(UserWarning, match="unknown coordinate system 99"):
        stored, got = _stored(tmp_path, _frame_record(99))
    np.testing.assert_array_equal(got.quats, stored.quats)
    stored, got = _stored(tmp_path, _frame_record(6))  # RDF: PLY's own axes
    np.testing.assert_array_equal(got.sh_rest, stored.sh_rest)


# --------------------------------------------------------------------------
# Bad files and errors
# --------------------------------------------------------------------------

def _raises(tmp_path, data: bytes, match: str, name: str = "bad.spz"):
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(SplatFormatError, match=re.escape(name) + ".*" + match):
        read_splats(path, format="spz")


def _v4_parts(data: bytes):
    count, toc = data[15], struct.unpack_from("<I", data, 16)[0]
    sizes = np.frombuffer(data, "<u8", 2 * count, toc).reshape(count, 2).astype(int)
    return toc, sizes, toc + 16 * count


def test_truncated_files(tmp_path):
    gz = _legacy(3)
    for cut in (5, 12, len(gz) // 2, len(gz) - 4):
        _raises(tmp_path, gz[:cut], "truncated gzip stream")
    _raises(tmp_path, gzip.compress(gzip.decompress(gz)[:40]),
            "truncated SPZ data: the colours of 2 splats need 6 bytes at byte 36")
    _raises(tmp_path, gzip.compress(b"NGSP\3\0\0\0"), "truncated SPZ header")
    _raises(tmp_path, gz + b"junk", "4 unexpected bytes after the end of the gzip stream")
    v4 = _v4()
    toc, sizes, start = _v4_parts(v4)
    _raises(tmp_path, v4[:20], "truncated SPZ header: 20 bytes")
    _raises(tmp_path, v4[:start - 3], "table of contents ends at byte")
    _raises(tmp_path, v4[:-3], r"truncated SPZ file: stream 5 \(sh\) needs")
    # A truncated ZSTD stream whose table entry was cut to match.
    last = sizes[-1, 0]
    cut = v4[:toc + 16 * 5] + struct.pack("<Q", last - 4) + v4[toc + 16 * 5 + 8:-4]
    _raises(tmp_path, cut, r"truncated ZSTD stream 5 \(sh\)")
    garbage = bytearray(v4)
    garbage[start:start + 8] = b"\xff" * 8
    _raises(tmp_path, bytes(garbage), r"ZSTD stream 0 \(positions\)")


def test_inconsistent_headers_and_tables(tmp_path):
    v4 = _v4()
    toc, sizes, start = _v4_parts(v4)
    wrong_size = v4[:toc + 8] + struct.pack("<Q", 17) + v4[toc + 16:]
    _raises(tmp_path, wrong_size, r"stream 0 \(positions\) is listed as 17 bytes uncompressed; 2 splats need 18")
    _raises(tmp_path, _v4(count=5), "lists 5 streams; 2 splats of SH degree 1 need 6")
    _raises(tmp_path, v4[:16] + struct.pack("<I", 16) + v4[20:], "inside the 32-byte header")
    _raises(tmp_path, v4 + b"\0\0", "2 unexpected bytes after the last SPZ stream")
    _raises(tmp_path, _v4(ext=b"\1\2\3", flags=2), r"truncated SPZ extension record")
    _raises(tmp_path, _v4(ext=_record(7, b"abc")[:-1], flags=2), "claims 3 bytes, only 2 remain")
    _raises(tmp_path, _legacy(3, flags=2, after=b"\1\2"), "truncated SPZ extension record")


def test_wrong_magic_version_and_degree(tmp_path):
    _raises(tmp_path, b"NGSX" + _v4()[4:], r"not an SPZ file: its first bytes b'NGSX'")
    _raises(tmp_path, gzip.compress(b"hello world, no splats"), r"gzip data starts with b'hell'")
    _raises(tmp_path, _v4(version=5), "unsupported SPZ version 5")
    _raises(tmp_path, _legacy(0), "unsupported SPZ version 0")
    _raises(tmp_path, _legacy(4), "version 4 inside gzip")
    _raises(tmp_path, _v4(degree=4), "SH degree 4 .*reads SH up to degree 3")
    _raises(tmp_path, _legacy(3, degree=4), "SH degree 4 .*up to degree 3")
    _raises(tmp_path, _v4(degree=5), "invalid SH degree 5")
    _raises(tmp_path, _legacy(3, fractional_bits=25), "invalid fractional bits 25")


def test_positions_out_of_range_name_the_splat_and_write_nothing(tmp_path):
    out = tmp_path / "keep.spz"
    out.write_bytes(b"old")
    src = real_splats()
    src.means[7] = [2048.0, 0.0, 0.0]
    with pytest.raises(SplatFormatError, match=r"keep\.spz: splat 7 is at \(2048, 0, 0\), outside"):
        write_splats(out, src)
    src.means[7] = [0.0, -2048.001, 0.0]
    with pytest.raises(SplatFormatError, match="splat 7"):
        write_spz(out, src, version=3)
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.spz"]
    src.means[7] = [2047.9998, -2048.0, 0.0]  # the edges themselves fit
    write_spz(out, src)
    np.testing.assert_allclose(read_splats(out).means[7], [2047.9998, -2048.0, 0.0], atol=0.5 / 4096)
    with pytest.raises(ValueError, match="version must be 2, 3 or 4"):
        write_spz(out, src, version=5)


def test_without_zstandard_v4_says_how_to_install_it(tmp_path, monkeypatch):
    write_spz(tmp_path / "a4.spz", real_splats())
    monkeypatch.setitem(sys.modules, "zstandard", None)
    with pytest.raises(SplatFormatError, match=r"a4\.spz.*pip install zstandard"):
        read_splats(tmp_path / "a4.spz")
    with pytest.raises(SplatFormatError, match=r"b4\.spz.*pip install zstandard"):
        write_splats(tmp_path / "b4.spz", real_splats())
    assert not (tmp_path / "b4.spz").exists()
    write_spz(tmp_path / "a3.spz", real_splats(), version=3)
    assert read_splats(tmp_path / "a3.spz").count == 500


def test_detected_by_content_under_any_extension(tmp_path):
    for source, name in ((PEER_V4, "scene.bin"), (PEER_V3, "scene.ply"), (PEER_V3, "scene")):
        path = tmp_path / name
        path.write_bytes(source.read_bytes())
        assert detect_format(path).name == "spz"
        assert read_splats(path).count == 500
