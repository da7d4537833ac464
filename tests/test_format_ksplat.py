"""GaussianSplats3D ``.ksplat``: files built by hand from the layout in
mlx3d/io/ksplat.py, files made by GaussianSplats3D itself, round trips through
our writer within the module's bounds at each compression level, the peer
(splat-transform reads .ksplat but does not write it) reading our files to the
same values, bad files, detection.

``data/formats/gs3d_200_level{L}_sh{D}.ksplat`` were made by
``@mkkellogg/gaussian-splats-3d`` 0.4.7 (with three 0.187.0) under node 20 from
the first 200 splats of ``opensplat_500.ply`` (read with ``read_splat_ply``,
sliced, written with ``write_splat_ply`` as ``first200.ply``), by this script
(``node mk.mjs first200.ply out.ksplat L D``)::

    import * as GS from '@mkkellogg/gaussian-splats-3d';
    import * as THREE from 'three';
    import * as fs from 'fs';
    const [,, input, output, level, degree] = process.argv;
    const data = fs.readFileSync(input);
    const buf = data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
    const arr = GS.PlyParser.parseToUncompressedSplatArray(buf, parseInt(degree));
    const gen = GS.SplatBufferGenerator.getStandardGenerator(1, parseInt(level), 0, new THREE.Vector3(), 5.0, 256);
    fs.writeFileSync(output, new Uint8Array(gen.generateFromUncompressedSplatArray(arr).bufferData));
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from format_cases import DATA, adversarial_splats, assert_close_splats, real_splats, rotations
from format_cases import splat_transform  # noqa: F401
from mlx3d.errors import SplatFormatError
from mlx3d.io import SplatArrays, detect_format, read_splat_ply, read_splats
from mlx3d.io.codec import SH_C0, sigmoid
from mlx3d.io.ksplat import bucket_order, read_ksplat, sniff_ksplat, write_ksplat

from core_marks import runs_no_kernel  # noqa: E402

pytestmark = runs_no_kernel  # file formats, datasets and packaging: no kernel of ours runs here

FIELDS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
DC = 0.5 / 255 / SH_C0 + 1e-6     # half an 8-bit colour step
ALPHA = 0.5 / 255 + 1e-7
STEP = 2.5 / 32767                # position step of the default 5.0 block


# --------------------------------------------------------------------------
# files built by hand
# --------------------------------------------------------------------------

def main_header(sections, splats, level, sh_range=(0.0, 0.0), version=(0, 1)) -> bytes:
    head = bytearray(4096)
    head[0:2] = bytes(version)
    struct.pack_into("<4IH", head, 4, sections, sections, splats, splats, level)
    struct.pack_into("<2f", head, 36, *sh_range)
    return bytes(head)


def section_header(count, degree, bucket_size=0, buckets=0, block=0.0, full=0, partial=0, qrange=0) -> bytes:
    sec = bytearray(1024)
    struct.pack_into("<4IfH", sec, 0, count, count, bucket_size, buckets, block, 12 if buckets else 0)
    struct.pack_into("<I", sec, 24, qrange)
    struct.pack_into("<2IH", sec, 32, full, partial, degree)
    return bytes(sec)


def test_level0_records_from_the_layout(tmp_path):
    rec = struct.pack("<3f3f4f4B9f", 1.0, 2.0, 3.0, 0.5, 1.0, 2.0, 0.5, 0.5, 0.5, 0.5, 255, 128, 0, 191,
                      *range(1, 10))
    path = tmp_path / "l0.ksplat"
    path.write_bytes(main_header(1, 1, 0) + section_header(1, 1) + rec)
    s = read_splats(path)
    assert s.count == 1 and s.sh_degree == 1
    np.testing.assert_array_equal(s.means, [[1, 2, 3]])
    np.testing.assert_allclose(s.scales, np.log([[0.5, 1.0, 2.0]]), atol=1e-7)
    np.testing.assert_array_equal(s.quats, [[0.5, 0.5, 0.5, 0.5]])  # w x y z as stored
    np.testing.assert_allclose(s.sh_dc[0, 0], (np.array([255, 128, 0]) / 255 - 0.5) / SH_C0, atol=1e-6)
    np.testing.assert_allclose(sigmoid(s.opacities), [191 / 255], atol=1e-6)
    # Degree 1 is stored channel by channel: r0 r1 r2 g0 g1 g2 b0 b1 b2.
    np.testing.assert_array_equal(s.sh_rest[0], [[1, 4, 7], [2, 5, 8], [3, 6, 9]])


def test_level1_buckets_from_the_layout(tmp_path):
    # Three splats, bucket size 2: one full bucket (splats 0, 1), one partial (splat 2).
    # Block 2.0 with range 32767: position = centre + (q - 32767) / 32767.
    centers = struct.pack("<6f", 10.0, 0.0, 0.0, -5.0, 5.0, 5.0)
    data = struct.pack("<I", 1) + centers
    recs = [((32767, 32767, 32767), (1.0, 0, 0, 0)),
            ((65534, 0, 32767 + 16384), (0, 1.0, 0, 0)),
            ((32767, 32767, 0), (0.5, 0.5, 0.5, 0.5))]
    for q, rot in recs:
        data += struct.pack("<3H", *q) + np.array([0.5, 1.0, 2.0, *rot], "<f2").tobytes() + bytes([0, 255, 51, 255])
    path = tmp_path / "l1.ksplat"
    path.write_bytes(main_header(1, 3, 1) + section_header(3, 0, 2, 2, 2.0, 1, 1) + data)
    s = read_splats(path)
    np.testing.assert_allclose(s.means, [[10, 0, 0], [11, -1, 16384 / 32767], [-5, 5, 4]], atol=1e-6)
    np.testing.assert_allclose(s.scales, np.log([[0.5, 1.0, 2.0]] * 3), atol=1e-7)
    np.testing.assert_allclose(rotations(s.quats), rotations(np.array([r for _, r in recs])), atol=1e-7)
    np.testing.assert_allclose(s.sh_dc[:, 0], [[-0.5 / SH_C0, 0.5 / SH_C0, (0.2 - 0.5) / SH_C0]] * 3, atol=1e-6)
    assert s.sh_degree == 0


def test_level2_sh_range_and_sections_of_different_degrees(tmp_path):
    rec0 = struct.pack("<3H3e4e4B", 32767, 32767, 32767, 1, 1, 1, 1, 0, 0, 0, 128, 128, 128, 255)
    rec1 = rec0 + bytes([0, 255, 51, 102, 153, 204, 0, 0, 255])
    sec0 = section_header(1, 0, 256, 1, 5.0, 0, 1)
    sec1 = section_header(1, 1, 256, 1, 5.0, 0, 1)
    bucket = struct.pack("<I3f", 1, 0.0, 0.0, 0.0)
    body = main_header(2, 2, 2, (-2.0, 2.0)) + sec0 + sec1 + bucket + rec0 + bucket + rec1
    path = tmp_path / "l2.ksplat"
    path.write_bytes(body)
    s = read_splats(path)
    assert s.count == 2 and s.sh_degree == 1
    np.testing.assert_array_equal(s.sh_rest[0], 0)  # the degree-0 section, padded
    q = np.array([0, 255, 51, 102, 153, 204, 0, 0, 255]).reshape(3, 3).T  # (coefficient, channel)
    np.testing.assert_allclose(s.sh_rest[1], -2 + q / 255 * 4, atol=1e-6)
    # A zero SH range in the header reads as -1.5 .. 1.5 (as splat-transform and GaussianSplats3D).
    path.write_bytes(main_header(2, 2, 2) + body[4096:])
    np.testing.assert_allclose(read_splats(path).sh_rest[1], -1.5 + q / 255 * 3, atol=1e-6)


# --------------------------------------------------------------------------
# round trips through our writer, within the module's bounds
# --------------------------------------------------------------------------

def _representable(s: SplatArrays, order) -> SplatArrays:
    """``s`` in file order with colours clamped to [0, 1] and SH cut to degree 2."""
    rgb = np.clip(0.5 + SH_C0 * s.sh_dc.astype(np.float64), 0.0, 1.0)
    return SplatArrays(
        means=s.means[order], scales=s.scales[order], quats=s.quats[order], opacities=s.opacities[order],
        sh_dc=((rgb - 0.5) / SH_C0).astype(np.float32)[order], sh_rest=s.sh_rest[order, :8])


def _check(got: SplatArrays, want: SplatArrays, level: int, sh_range, what: str) -> None:
    if level == 0:
        assert_close_splats(got, want, scales=np.inf, rotation=1e-6, alpha=ALPHA, sh_dc=DC, what=what)
        np.testing.assert_array_equal(got.means, want.means)
        np.testing.assert_array_equal(got.sh_rest, want.sh_rest)
        bound = 6e-8 + np.spacing(np.abs(want.scales)) / 2
        assert np.all(np.abs(got.scales - want.scales) <= bound), what
        return
    pos_bound = STEP / 2 + np.spacing(np.abs(want.means)) + 1e-9
    assert np.all(np.abs(got.means - want.means) <= pos_bound), f"{what}: positions"
    assert_close_splats(got, want, means=np.inf, scales=np.inf, sh_rest=np.inf, rotation=2e-3, alpha=ALPHA, sh_dc=DC,
                        what=what)
    lin, want_lin = np.exp(got.scales.astype(np.float64)), np.minimum(np.exp(want.scales.astype(np.float64)), 65504)
    assert np.all(np.abs(lin - want_lin) <= np.maximum(2 ** -11 * want_lin, 2 ** -25) + 1e-6 * want_lin), \
        f"{what}: scales"
    v = want.sh_rest.astype(np.float64)
    if level == 1:
        bound = np.maximum(2 ** -11 * np.abs(v), 2 ** -25)
    else:
        bound = (sh_range[1] - sh_range[0]) / 510 + 1e-6
    assert np.all(np.abs(got.sh_rest - v) <= bound), f"{what}: sh_rest"


@pytest.mark.parametrize("level", [0, 1, 2])
@pytest.mark.parametrize("case", ["real", "adversarial"])
def test_round_trip_within_bounds(tmp_path, level, case):
    src = real_splats(2) if case == "real" else adversarial_splats(degree=2, span=1e4)
    path = tmp_path / "a.ksplat"
    write_ksplat(path, src, level=level)
    got = read_splats(path)
    order = np.arange(src.count) if level == 0 else bucket_order(src.means)[0]
    sh_range = struct.unpack_from("<2f", path.read_bytes(), 36)
    _check(got, _representable(src, order), level, sh_range, f"{case} level {level}")
    size = 4096 + 1024 + src.count * {0: 140, 1: 72, 2: 48}[level]
    assert path.stat().st_size == size + (0 if level == 0 else 16 * len(bucket_order(src.means)[2])
                                          + 12 * bucket_order(src.means)[3])


def test_buckets_hold_their_splats_and_sh_degree_3_is_dropped(tmp_path):
    src = adversarial_splats(n=700, degree=3, span=12.0)
    src.means[:600] = src.means[:600] * 0.01  # 600 splats in one block: two full buckets of 256 and a partial one
    with pytest.warns(UserWarning, match="degree 3 is not written"):
        write_ksplat(tmp_path / "b.ksplat", src, level=1)
    data = (tmp_path / "b.ksplat").read_bytes()
    count, _, size, buckets, block = struct.unpack_from("<4If", data, 4096)
    full, partial, degree = struct.unpack_from("<2IH", data, 4096 + 32)
    assert (count, size, block, degree) == (700, 256, 5.0, 2) and full >= 2 and full + partial == buckets
    lengths = np.frombuffer(data, "<u4", partial, 5120)
    assert full * 256 + lengths.sum() == 700 and np.all((lengths > 0) & (lengths < 256))
    order, centers, _, _ = bucket_order(src.means)
    b = np.concatenate([np.arange(full * 256) // 256, np.repeat(full + np.arange(partial), lengths)])
    assert np.all(np.abs(src.means[order] - centers[b]) <= 2.5 + 1e-9)
    assert read_splats(tmp_path / "b.ksplat").sh_degree == 2


# --------------------------------------------------------------------------
# GaussianSplats3D's files and the peer
# --------------------------------------------------------------------------

@pytest.mark.parametrize("level, degree", [(0, 1), (1, 2), (2, 2)])
def test_files_made_by_gaussian_splats_3d(level, degree):
    got = read_splats(DATA / f"gs3d_200_level{level}_sh{degree}.ksplat")
    src = real_splats(degree)
    src = SplatArrays(**{k: getattr(src, k)[:200] for k in FIELDS})
    # The generator reorders the splats (by bucket, even at level 0): match them by position.
    d = ((got.means[:, None, :].astype(np.float64) - src.means[None]) ** 2).sum(axis=2)
    match = d.argmin(axis=1)
    assert len(set(match.tolist())) == 200
    want = _representable(src, match)
    # Its bounds: colours and SH floored to 8 bits (one step), half floats truncated (one ulp).
    one_step = dict(alpha=1 / 255 + 1e-7, sh_dc=1 / 255 / SH_C0 + 1e-6)
    if level == 0:
        assert_close_splats(got, want, scales=1e-6, rotation=1e-6, **one_step, what="gs3d level 0")
        return
    lo, hi = struct.unpack_from("<2f", (DATA / f"gs3d_200_level{level}_sh{degree}.ksplat").read_bytes(), 36)
    sh = 2 ** -10 * np.abs(want.sh_rest).max() + 1e-6 if level == 1 else (hi - lo) / 255 + 1e-6
    assert_close_splats(got, want, means=STEP + 1e-6, scales=2 ** -10 + 1e-6, rotation=2e-3, sh_rest=sh,
                        **one_step, what=f"gs3d level {level}")


@pytest.mark.parametrize("level", [0, 1, 2])
def test_peer_reads_our_files_to_the_same_values(tmp_path, splat_transform, level):  # noqa: F811
    src = adversarial_splats(degree=2, span=1e3)
    path = tmp_path / "ours.ksplat"
    write_ksplat(path, src, level=level)
    peer = read_splat_ply(splat_transform.convert(path, tmp_path / "peer.ply"))
    ours = read_splats(path)
    for key in FIELDS:
        np.testing.assert_array_equal(getattr(peer, key), getattr(ours, key), err_msg=key)


def test_peer_reads_gaussian_splats_3d_files_as_we_do(tmp_path, splat_transform):  # noqa: F811
    for path in sorted(DATA.glob("gs3d_*.ksplat")):
        peer = read_splat_ply(splat_transform.convert(path, tmp_path / "peer.ply"))
        ours = read_splats(path)
        for key in FIELDS:
            np.testing.assert_array_equal(getattr(peer, key), getattr(ours, key), err_msg=f"{path.name} {key}")


# --------------------------------------------------------------------------
# bad files and detection
# --------------------------------------------------------------------------

def _good(tmp_path, level=1) -> bytes:
    write_ksplat(tmp_path / "good.ksplat", real_splats(1), level=level)
    return (tmp_path / "good.ksplat").read_bytes()


def _expect(tmp_path, name, data, message):
    path = tmp_path / f"{name}.ksplat"
    path.write_bytes(data)
    with pytest.raises(SplatFormatError, match=rf"{name}\.ksplat.*{message}"):
        read_ksplat(path)


def test_truncated_files_are_named(tmp_path):
    data = _good(tmp_path)
    for cut, message in [(100, "main header"), (4096 + 500, "section header 0"),
                         (5120 + 10, "bucket"), (len(data) - 7, "section 0's 500 splats")]:
        _expect(tmp_path, f"cut{cut}", data[:cut], rf"truncated .*{message}")


def test_inconsistent_headers_are_named(tmp_path):
    data = bytearray(_good(tmp_path))

    def patched(offset, fmt, *values):
        bad = bytearray(data)
        struct.pack_into(fmt, bad, offset, *values)
        return bytes(bad)

    _expect(tmp_path, "v10", patched(0, "<BB", 1, 0), r"version 1\.0")
    _expect(tmp_path, "v00", patched(0, "<BB", 0, 0), r"version 0\.0")
    _expect(tmp_path, "level", patched(20, "<H", 3), "compression level 3")
    _expect(tmp_path, "count", patched(16, "<I", 499), "says 499 splats but its 1 sections hold 500")
    _expect(tmp_path, "room", patched(4096 + 4, "<I", 400), "holds 500 splats but has room for 400")
    _expect(tmp_path, "degree", patched(4096 + 40, "<H", 4), "SH degree 4")
    full, partial = struct.unpack_from("<2I", data, 4096 + 32)
    _expect(tmp_path, "partial", patched(5120, "<I", 1), "partial buckets hold")
    _expect(tmp_path, "buckets", patched(4096 + 12, "<I", full + partial - 1), "splats refer to bucket")
    assert read_ksplat(tmp_path / "good.ksplat").count == 500


def test_detection_by_content(tmp_path):
    data = _good(tmp_path, level=0)
    (tmp_path / "renamed.bin").write_bytes(data)
    assert read_splats(tmp_path / "renamed.bin").count == 500
    assert sniff_ksplat(data[:4096], str(tmp_path / "renamed.bin"))
    # Never a .splat file (those have no header), nor a header whose counts do not fit the file.
    assert not sniff_ksplat(data[:4096], str(tmp_path / "x.splat"))
    (tmp_path / "short.bin").write_bytes(data[:6000])
    assert not sniff_ksplat(data[:4096], str(tmp_path / "short.bin"))
    assert not sniff_ksplat(bytes(4096), str(tmp_path / "renamed.bin"))
    # A .splat file is read as one even when its first bytes make a .ksplat header.
    (tmp_path / "a.splat").write_bytes(data[:len(data) // 32 * 32])
    assert detect_format(tmp_path / "a.splat").name == "splat"
