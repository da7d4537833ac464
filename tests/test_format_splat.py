"""antimatter15 ``.splat``: spec-derived records, round trips within the
format's bounds (mlx3d/io/splat.py), the peer reading our files, bad files."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from format_cases import adversarial_splats, assert_close_splats, real_splats, splat_transform  # noqa: F401
from mlx3d.errors import NonFiniteError, SplatFormatError
from mlx3d.io import SplatArrays, read_splat_ply, read_splats, write_splats
from mlx3d.io.codec import SH_C0

from core_marks import runs_no_kernel  # noqa: E402

pytestmark = runs_no_kernel  # file formats, datasets and packaging: no kernel of ours runs here

# The module's stated bounds (half an 8-bit step, in each field's own units).
BOUNDS = dict(means=0.0, scales=1e-6, rotation=0.02, alpha=0.5 / 255 + 1e-7, sh_dc=0.5 / 255 / SH_C0 + 1e-6)


def _representable(s: SplatArrays) -> SplatArrays:
    """``s`` with its colours clamped to [0, 1] and SH cut to degree 0: what .splat can hold."""
    rgb = np.clip(0.5 + SH_C0 * s.sh_dc.astype(np.float64), 0.0, 1.0)
    return SplatArrays(
        means=s.means, scales=s.scales, quats=s.quats, opacities=s.opacities,
        sh_dc=((rgb - 0.5) / SH_C0).astype(np.float32), sh_rest=np.zeros((s.count, 0, 3), np.float32))


def test_record_layout_from_the_format_description(tmp_path):
    # One record built byte by byte: position, linear scale, RGBA, quaternion w x y z as 128q+128.
    rec = struct.pack("<3f3f4B4B", 1.5, -2.0, 3.25, 0.5, 1.0, 2.0, 255, 128, 0, 191, 128, 255, 128, 128)
    path = tmp_path / "one.splat"
    path.write_bytes(rec)
    s = read_splats(path)
    np.testing.assert_array_equal(s.means, [[1.5, -2.0, 3.25]])
    np.testing.assert_allclose(s.scales, np.log([[0.5, 1.0, 2.0]]), atol=1e-7)
    np.testing.assert_allclose(s.sh_dc[0, 0], (np.array([255, 128, 0]) / 255 - 0.5) / SH_C0, atol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-s.opacities)), [191 / 255], atol=1e-6)
    # (128, 255, 128, 128) -> (0, 127/128, 0, 0) -> a half turn about x.
    np.testing.assert_allclose(s.quats, [[0.0, 1.0, 0.0, 0.0]], atol=1e-7)
    assert s.sh_degree == 0


@pytest.mark.parametrize("case", ["real", "adversarial"])
def test_round_trip_within_bounds(tmp_path, case):
    src = real_splats() if case == "real" else adversarial_splats(span=1e4)
    path = tmp_path / "a.splat"
    write_splats(path, src)
    assert path.stat().st_size == 32 * src.count
    got = read_splats(path)
    assert_close_splats(got, _representable(src), **BOUNDS, what=case)
    # Saving what was read again does not drift: position, scale and colour
    # bytes are the same; a renormalised rotation moves by at most one step.
    again = tmp_path / "b.splat"
    write_splats(again, got)
    first, second = (np.frombuffer(p.read_bytes(), np.uint8).reshape(-1, 32) for p in (path, again))
    np.testing.assert_array_equal(first[:, :28], second[:, :28])
    assert np.abs(first[:, 28:].astype(int) - second[:, 28:]).max() <= 1


def test_peer_reads_our_files(tmp_path, splat_transform):  # noqa: F811
    src = real_splats()
    ours = tmp_path / "ours.splat"
    write_splats(ours, src)
    back = splat_transform.convert(ours, tmp_path / "peer.ply")
    peer = read_splat_ply(back)
    # The peer decodes rotations as b/127.5 - 1 (we use (b - 128)/128): both within the bound.
    assert_close_splats(peer, read_splats(ours), **BOUNDS, what="peer")


def test_bad_files_are_named_and_nothing_is_written(tmp_path):
    short = tmp_path / "short.splat"
    short.write_bytes(b"\0" * 70)
    with pytest.raises(SplatFormatError, match=r"short\.splat.*70 bytes.*2 whole records and 6 bytes over"):
        read_splats(short)
    empty = tmp_path / "empty.splat"
    empty.write_bytes(b"")
    with pytest.raises(SplatFormatError, match="empty"):
        read_splats(empty)

    out = tmp_path / "keep.splat"
    out.write_bytes(b"old")
    bad = real_splats()
    bad.means[3, 1] = np.nan
    with pytest.raises(NonFiniteError, match=r"means.*splat 3"):
        write_splats(out, bad)
    assert out.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.splat", "keep.splat", "short.splat"]


def test_dropping_sh_and_extras_is_said(tmp_path):
    src = real_splats()
    src.extra["confidence"] = np.ones(src.count, np.float32)
    with pytest.warns(UserWarning, match="confidence"):
        write_splats(tmp_path / "a.splat", src)
    assert read_splats(tmp_path / "a.splat", sh_degree=2).sh_rest.shape == (src.count, 8, 3)


def test_a_formats_own_writing_options_and_a_wrong_one(tmp_path):
    from mlx3d.io import format_for_path

    assert format_for_path("x.spz").options() == ("version",) and format_for_path("x.splat").options() == ()
    write_splats(tmp_path / "v2.spz", real_splats(1), version=2)
    assert read_splats(tmp_path / "v2.spz").count == 500
    with pytest.raises(ValueError, match=r"a\.splat.*no writing option 'version'.*takes none"):
        write_splats(tmp_path / "a.splat", real_splats(), version=3)
    assert not (tmp_path / "a.splat").exists()
