"""Tile binning, C++ ('cpu') and MLX ('mlx'), against numpy constructions of the same lists and each other."""

import numpy as np
import pytest

import mlx.core as mx

from mlx3d import native
from mlx3d.errors import ExtensionBuildError
from mlx3d.render import bin_gaussians, bin_tiles
from mlx3d.render.binning import tile_extents
from mlx3d.render.raster_reference import rasterize_reference

from core_marks import needs_core
BACKENDS = [pytest.param("cpu", marks=needs_core), "mlx"]


def brute_bins(means2d, radii, depths, width, height, tile):
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    per_tile = [[] for _ in range(tiles_x * tiles_y)]
    for g, ((mx_, my_), r, d) in enumerate(zip(means2d, radii, depths)):
        if r <= 0:
            continue
        for ty in range(tiles_y):
            for tx in range(tiles_x):
                if np.floor((mx_ - r) / tile) <= tx <= np.floor((mx_ + r) / tile) and np.floor((my_ - r) / tile) <= ty <= np.floor((my_ + r) / tile):
                    per_tile[ty * tiles_x + tx].append((np.float32(d), g))
    offsets, ids = [0], []
    for entries in per_tile:
        ids += [g for _, g in sorted(entries)]
        offsets.append(len(ids))
    return np.array(offsets), np.array(ids, dtype=np.int64)


def formula_extents(radii, conics=None, opacities=None) -> np.ndarray:
    """(N,2) float32 half-extents by the module docstring's formula in float64 numpy, rounded to float32."""
    r = np.asarray(radii, np.float32).astype(np.float64)
    if conics is None:
        return np.stack([r, r], 1).astype(np.float32)
    con, o = np.asarray(conics, np.float32).astype(np.float64), np.asarray(opacities, np.float32).astype(np.float64)
    det = con[:, 0] * con[:, 2] - con[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        k = 2.0 * np.log(np.maximum(255.0 * o, 1e-30))
        live = (r > 0) & (det > 0) & (k > 0)
        inv = np.where(live, 1.0 / np.where(live, det, 1.0), 0.0)
        ext = np.minimum(np.sqrt(np.maximum(k, 0.0)[:, None] * np.stack([con[:, 2] * inv, con[:, 0] * inv], axis=1)) + 1.0, r[:, None])
    return np.where(live[:, None], ext, 0.0).astype(np.float32)


def numpy_bins(means2d, ext, depths, width, height, tile):
    """(tile_offsets, flatten_ids) for half-extents ``ext`` (N,2): rectangles in float64, entries sorted by
    (tile, depth, index) with numpy's float order (-0 == 0, NaN last)."""
    tiles = np.array([-(-width // tile), -(-height // tile)])
    m, e = np.asarray(means2d, np.float32).astype(np.float64), np.asarray(ext, np.float64)
    with np.errstate(invalid="ignore"):
        def clamp(v):
            return np.where(v > 0, np.minimum(v, tiles), 0).astype(np.int64)

        lo, hi = clamp(np.floor((m - e) / tile)), clamp(np.floor((m + e) / tile) + 1)
    count = np.where((e > 0).all(1), np.prod(hi - lo, axis=1), 0)
    gauss = np.repeat(np.arange(len(m)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    width_g = (hi - lo)[gauss, 0]
    tile_ids = (lo[gauss, 1] + local // width_g) * tiles[0] + lo[gauss, 0] + local % width_g
    order = np.lexsort((gauss, np.asarray(depths, np.float32)[gauss], tile_ids))
    return np.searchsorted(tile_ids[order], np.arange(tiles.prod() + 1)), gauss[order]


def as_np(bins):
    return np.array(bins.tile_offsets), np.array(bins.flatten_ids)


def assert_same(bins, offsets, ids):
    got_offsets, got_ids = as_np(bins)
    assert got_offsets.dtype == np.int32 and got_ids.dtype == np.int32
    np.testing.assert_array_equal(got_offsets, offsets)
    np.testing.assert_array_equal(got_ids, ids)


def random_scene(rng, n, width, height):
    """Random means2d (some off screen), radii (some 0, some huge or infinite), float32 depths with ties,
    -0, 0, negative and NaN."""
    means2d = rng.uniform(-40, [width + 40, height + 40], (n, 2)).astype(np.float32)
    means2d[rng.random(n) < 0.05] += rng.choice([-1e4, 1e4], 2).astype(np.float32)  # far off screen
    radii = rng.integers(0, 30, n).astype(np.float32)
    radii[rng.random(n) < 0.05] = rng.uniform(0.01, 3)
    radii[rng.random(n) < 0.01] = 1e30
    radii[rng.random(n) < 0.01] = np.inf
    depths = np.round(rng.uniform(-1, 6, n), 1).astype(np.float32)  # ties
    for value, share in ((np.nan, 0.05), (-0.0, 0.05), (0.0, 0.05)):
        depths[rng.random(n) < share] = value
    return means2d, radii, depths


def random_conics(rng, n, sigma=(0.5, 8)):
    """Conics (N,3) of random anisotropic covariances with σ in ``sigma`` px, their 3σ radii (N,), opacities (N,)."""
    angle = rng.uniform(0, np.pi, n)
    s1, s2 = rng.uniform(*sigma, n), rng.uniform(sigma[0], sigma[1] / 3, n)
    c, s = np.cos(angle), np.sin(angle)
    cov = np.stack([c * c * s1**2 + s * s * s2**2, c * s * (s1**2 - s2**2), s * s * s1**2 + c * c * s2**2], 1) + [0.3, 0, 0.3]
    det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
    conics = (np.stack([cov[:, 2], -cov[:, 1], cov[:, 0]], 1) / det[:, None]).astype(np.float32)
    lam = 0.5 * (cov[:, 0] + cov[:, 2]) + np.sqrt(0.25 * (cov[:, 0] - cov[:, 2]) ** 2 + cov[:, 1] ** 2)
    opac = rng.uniform(0.001, 0.99, n).astype(np.float32)
    return conics, np.ceil(3 * np.sqrt(lam)).astype(np.float32), opac


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed, width, height, tile", [(0, 40, 30, 16), (1, 64, 64, 16), (2, 33, 17, 8)])
def test_bins_match_brute_force(seed, width, height, tile, backend):
    rng = np.random.default_rng(seed)
    n = 150
    means2d = rng.uniform(-20, width + 20, (n, 2))
    radii = rng.integers(0, 25, n)
    depths = rng.uniform(0.1, 10, n)
    depths[:10] = depths[10]  # ties sort by Gaussian index
    bins = bin_tiles(means2d, radii, depths, width, height, tile, backend=backend)
    assert_same(bins, *brute_bins(means2d, radii, depths, width, height, tile))
    assert (bins.tiles_x, bins.tiles_y) == (-(-width // tile), -(-height // tile))


@needs_core
def test_threaded_binning_matches_a_numpy_oracle_for_any_thread_count():
    # enough Gaussians that every thread gets a chunk (16,384 at least each), with depth ties and culled ones
    from thread_counts import per_thread_count

    rng = np.random.default_rng(5)
    n, width, height, tile = 70_000, 320, 200, 16
    means2d = rng.uniform(-10, [width + 10, height + 10], (n, 2))
    radii = rng.integers(0, 20, n)
    depths = np.round(rng.uniform(0.1, 5, n), 2)  # many ties: they sort by index
    offsets, ids = numpy_bins(means2d, formula_extents(radii), depths, width, height, tile)
    results = per_thread_count(lambda: bin_tiles(means2d, radii, depths, width, height, tile, backend="cpu"), (1, 2, 3, 5))
    for bins in results:
        assert_same(bins, offsets, ids)


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_and_all_culled(backend):
    bins = bin_tiles(np.zeros((5, 2)), np.zeros(5), np.ones(5), 40, 30, backend=backend)
    assert np.array(bins.tile_offsets).tolist() == [0] * 7 and bins.flatten_ids.size == 0
    bins = bin_tiles(np.zeros((0, 2)), np.zeros(0), np.zeros(0), 40, 30, backend=backend)
    assert np.array(bins.tile_offsets).tolist() == [0] * 7 and bins.flatten_ids.size == 0
    assert bins.tile_offsets.dtype == bins.flatten_ids.dtype == mx.int32


@pytest.mark.parametrize("backend", BACKENDS)
def test_bad_arguments(backend):
    with pytest.raises(ValueError, match="tile_size"):
        bin_tiles(np.zeros((1, 2)), np.ones(1), np.ones(1), 8, 8, tile_size=0, backend=backend)
    with pytest.raises(ValueError, match="depths"):
        bin_tiles(np.zeros((2, 2)), np.ones(2), np.ones(3), 8, 8, backend=backend)
    with pytest.raises(ValueError, match="width"):
        bin_tiles(np.zeros((1, 2)), np.ones(1), np.ones(1), 0, 8, backend=backend)


@pytest.mark.parametrize(
    "seed, width, height, tile", [(0, 40, 30, 16), (1, 97, 61, 8), (2, 200, 120, 32), (3, 16, 16, 16), (4, 1, 1, 8), (5, 130, 33, 16)]
)
def test_mlx_bins_match_the_numpy_oracle_and_the_native_bins(seed, width, height, tile):
    """Bitwise equal ids and offsets: culled, off-screen, huge and infinite radii, NaN / -0 / tied depths."""
    rng = np.random.default_rng(seed)
    for n in (1, 3, 2000):
        means2d, radii, depths = random_scene(rng, n, width, height)
        offsets, ids = numpy_bins(means2d, formula_extents(radii), depths, width, height, tile)
        bins = bin_tiles(mx.array(means2d), mx.array(radii), mx.array(depths), width, height, tile, backend="mlx")
        assert_same(bins, offsets, ids)
        if native.available():
            assert_same(bin_tiles(means2d, radii, depths, width, height, tile, backend="cpu"), offsets, ids)
    assert np.isnan(depths[ids]).any() and (depths[ids] == 0).any() and np.isinf(radii[ids]).any()  # the edge cases are binned


@pytest.mark.parametrize("tile", [7, 8, 10, 16, 32])
def test_mlx_rectangles_round_like_double_at_tile_borders(tile):
    """Means at and one or two float32 ulps around m ± r = a tile border (and a subnormal centre, where the
    double sum rounds onto the border): the rectangles of the oracle's float64 arithmetic."""
    rng = np.random.default_rng(tile)
    n, width, height = 3000, 200, 150
    radii = np.where(rng.random(n) < 0.5, rng.integers(1, 40, n), rng.uniform(0.01, 40, n)).astype(np.float32)
    borders = (rng.integers(-2, 30, (n, 2)) * tile).astype(np.float64)
    means2d = (borders + rng.choice([-1, 1], (n, 2)) * radii[:, None]).astype(np.float32)
    for _ in range(2):
        step = rng.integers(-1, 2, (n, 2))
        means2d = np.where(step != 0, np.nextafter(means2d, np.where(step > 0, np.inf, -np.inf).astype(np.float32)), means2d)
    means2d[:20, 1] = np.float32(1e-45) * rng.choice([-1, 1], 20)
    radii[:20] = tile * rng.integers(1, 3, 20)
    depths = rng.integers(0, 20, n).astype(np.float32)
    offsets, ids = numpy_bins(means2d, formula_extents(radii), depths, width, height, tile)
    assert_same(bin_tiles(means2d, radii, depths, width, height, tile, backend="mlx"), offsets, ids)
    if native.available():
        assert_same(bin_tiles(means2d, radii, depths, width, height, tile, backend="cpu"), offsets, ids)


def max_alpha_in_tiles(means2d, conics, opac, gauss, tiles, tiles_x, tile):
    """Per (Gaussian, tile) pair: the largest alpha o·exp(-½ dᵀ conic d) over the tile's pixel centres (float64)."""
    px = np.arange(tile) + 0.5
    out = []
    for g, t in zip(gauss, tiles):
        dx = (t % tiles_x) * tile + px[None, :] - means2d[g, 0]
        dy = (t // tiles_x) * tile + px[:, None] - means2d[g, 1]
        a, b, c = conics[g].astype(np.float64)
        out.append(opac[g] * np.exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy).max())
    return np.array(out)


def entry_set(offsets, ids):
    return {(int(t), int(g)) for t in range(len(offsets) - 1) for g in ids[offsets[t]:offsets[t + 1]]}


def assert_same_image(means2d, conics, opac, bins_a, bins_b, width, height, tile):
    """rasterize_reference with (tile_offsets, flatten_ids, ...) ``bins_a`` and ``bins_b``: the same image and alpha."""
    colors = mx.array(np.random.default_rng(0).uniform(0, 1, (len(means2d), 3)).astype(np.float32))
    args = (mx.array(means2d), mx.array(conics), colors, mx.array(opac))
    a = rasterize_reference(*args, *tuple(bins_a)[:2], width, height, tile)
    b = rasterize_reference(*args, *tuple(bins_b)[:2], width, height, tile)
    np.testing.assert_array_equal(np.array(a[0]), np.array(b[0]))
    np.testing.assert_array_equal(np.array(a[1]), np.array(b[1]))


@pytest.mark.parametrize("seed, width, height, tile", [(0, 96, 80, 16), (1, 75, 50, 8), (2, 130, 70, 32)])
def test_mlx_bins_with_conics_match_the_double_extents_up_to_invisible_entries(seed, width, height, tile):
    """The float32 extents (within 2 ulps of the double ones) bin as the double ones do but for entries whose
    alpha stays below 1/255 on every pixel of the tile; the rendered images are equal."""
    rng = np.random.default_rng(seed)
    n = 1500
    means2d, _, depths = random_scene(rng, n, width, height)
    conics, radii, opac = random_conics(rng, n)
    radii[:30] = 0
    opac[30:60] = np.float32(1 / 255) * (1 + rng.integers(-3, 4, 30) * 2.0**-23)  # around 255·o = 1
    want = formula_extents(radii, conics, opac)
    got = tile_extents(radii, conics, opac, backend="mlx")
    np.testing.assert_array_equal(got > 0, want > 0)
    assert (np.abs(got.astype(np.float64) - want) <= 2 * np.spacing(want)).all()  # float32 ulps
    offsets, ids = numpy_bins(means2d, want, depths, width, height, tile)
    bins = bin_tiles(means2d, radii, depths, width, height, tile, conics, opac, backend="mlx")
    if native.available():
        assert_same(bin_tiles(means2d, radii, depths, width, height, tile, conics, opac, backend="cpu"), offsets, ids)
    extra = entry_set(offsets, ids) ^ entry_set(*as_np(bins))
    tiles_x = -(-width // tile)
    if extra:
        alpha = max_alpha_in_tiles(means2d, conics, opac, [g for _, g in extra], [t for t, _ in extra], tiles_x, tile)
        assert (alpha < 1 / 255).all()
    else:  # the same lists in the same order
        assert_same(bins, offsets, ids)
    assert_same_image(means2d, conics, opac, (mx.array(offsets.astype(np.int32)), mx.array(ids.astype(np.int32))), bins, width, height, tile)


def test_float32_extents_across_a_tile_border_change_no_pixel():
    """Gaussians placed so that a tile border lies between the float32 and the double extent: the two bins
    differ, only by entries whose alpha stays below 1/255 on the whole tile, and render the same image."""
    rng = np.random.default_rng(7)
    width, height, tile, n = 64, 48, 16, 20_000
    conics, _, opac = random_conics(rng, n, sigma=(0.5, 4))
    radii = np.full(n, 100, np.float32)  # the ellipse's box binds
    want = formula_extents(radii, conics, opac)[:, 0].astype(np.float64)
    got = tile_extents(radii, conics, opac, backend="mlx")[:, 0].astype(np.float64)
    means_x = np.float32(tile) - np.maximum(want, got).astype(np.float32)  # m + e just at the border x = 16
    for _ in range(3):  # step m until the border lies between m + got and m + want, where it can
        lo = np.minimum(means_x + want, means_x + got)
        means_x = np.where(lo >= tile, np.nextafter(means_x, np.float32(-np.inf)), means_x)
    lo, hi = np.minimum(means_x + want, means_x + got), np.maximum(means_x + want, means_x + got)
    keep = np.flatnonzero((lo < tile) & (hi >= tile))[:60]
    assert len(keep) >= 20
    means2d = np.stack([means_x[keep], rng.uniform(4, height - 4, len(keep))], 1).astype(np.float32)
    conics, opac, radii, depths = conics[keep], opac[keep], radii[keep], rng.uniform(1, 5, len(keep)).astype(np.float32)
    oracle = numpy_bins(means2d, formula_extents(radii, conics, opac), depths, width, height, tile)
    bins = bin_tiles(means2d, radii, depths, width, height, tile, conics, opac, backend="mlx")
    extra = entry_set(*oracle) ^ entry_set(*as_np(bins))
    assert len(extra) >= 20
    alpha = max_alpha_in_tiles(means2d, conics, opac, [g for _, g in extra], [t for t, _ in extra], -(-width // tile), tile)
    assert (alpha < 1 / 255).all()
    assert_same_image(means2d, conics, opac, (mx.array(oracle[0].astype(np.int32)), mx.array(oracle[1].astype(np.int32))), bins, width, height, tile)


def test_extents_match_the_formula_in_numpy():
    """The half-extents against the module docstring's formula in float64 numpy over random conics with
    the edge cases: det <= 0, 255 o <= 1, r = 0, r binding, nearly singular conics, o next to 1/255. The
    C++ ones bit for bit after rounding to float32; the MLX float32 ones zero exactly where those are, else
    within 2 ulps."""
    rng = np.random.default_rng(11)
    n = 20_000
    radii = rng.integers(0, 40, n).astype(np.float32)
    conics = np.stack([rng.uniform(1e-4, 2, n), rng.uniform(-1, 1, n), rng.uniform(1e-4, 2, n)], 1).astype(np.float32)
    near = slice(0, 2000)  # b² within a few ulps of a c: det's sign decided by the rounding
    conics[near, 1] = (np.sqrt(conics[near, 0].astype(np.float64) * conics[near, 2]) * (1 + rng.uniform(-1e-6, 1e-6, 2000))).astype(np.float32)
    opac = rng.uniform(0, 1, n).astype(np.float32)
    opac[:50] = 1 / 255  # reaches nothing
    opac[50:100] = np.float32(1 / 255) * (1 + rng.integers(-4, 5, 50) * 2.0**-23)
    want = formula_extents(radii, conics, opac)
    live = want[:, 0] > 0
    r = radii.astype(np.float64)[:, None]
    assert (~live).sum() > 1000 and (want[live] == r[live]).any() and (want[live] < r[live]).any()
    assert 0 < (want[near, 0] > 0).sum() < 2000
    got = tile_extents(radii, conics, opac, backend="mlx")
    np.testing.assert_array_equal(got > 0, want > 0)
    assert (np.abs(got.astype(np.float64) - want) <= 2 * np.spacing(want)).all()  # float32 ulps
    np.testing.assert_array_equal(tile_extents(radii, backend="mlx"), np.stack([radii, radii], 1))
    if native.available():
        np.testing.assert_array_equal(tile_extents(radii, conics, opac, backend="cpu"), want)
        np.testing.assert_array_equal(tile_extents(radii, backend="cpu"), np.stack([radii, radii], 1))


@pytest.mark.parametrize("backend", BACKENDS)
def test_opacity_aware_extents_change_no_pixel(backend):
    """Tighter tile extents drop only entries every pixel would skip: identical images, fewer entries."""
    rng = np.random.default_rng(3)
    n, width, height = 400, 96, 80
    means2d = mx.array(rng.uniform(0, 96, (n, 2)).astype(np.float32))
    conics, radii, opac = random_conics(rng, n, sigma=(1, 12))  # some faint Gaussians: 255·o <= 1 reaches no tile
    opac[:20] = 0.003
    depths = rng.uniform(1, 5, n)
    loose = bin_tiles(means2d, radii, depths, width, height, backend=backend)
    tight = bin_tiles(means2d, radii, depths, width, height, conics=mx.array(conics), opacities=opac, backend=backend)
    assert tight.flatten_ids.size < loose.flatten_ids.size
    assert not np.isin(np.arange(20), np.array(tight.flatten_ids)).any()
    if backend == "cpu":
        from mlx3d.render.raster_cpu import rasterize_cpu

        colors = mx.array(rng.uniform(0, 1, (n, 3)).astype(np.float32))
        a = rasterize_cpu(means2d, mx.array(conics), colors, mx.array(opac), loose.tile_offsets, loose.flatten_ids, width, height)
        b = rasterize_cpu(means2d, mx.array(conics), colors, mx.array(opac), tight.tile_offsets, tight.flatten_ids, width, height)
        np.testing.assert_array_equal(np.array(a[0]), np.array(b[0]))
        np.testing.assert_array_equal(np.array(a[1]), np.array(b[1]))
    else:
        assert_same_image(np.array(means2d), conics, opac, loose, tight, width, height, 16)
    ext = tile_extents(radii, conics, opac, backend=backend)
    assert (ext <= radii[:, None] + 1e-6).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_bin_gaussians_takes_a_backend(backend):
    rng = np.random.default_rng(4)
    means2d, radii, depths = random_scene(rng, 300, 50, 40)
    sorted_ids, ranges, tiles_x, tiles_y = bin_gaussians(means2d, radii, depths, 50, 40, backend=backend)
    offsets, ids = numpy_bins(means2d, formula_extents(radii), depths, 50, 40, 16)
    np.testing.assert_array_equal(np.array(sorted_ids), ids)
    np.testing.assert_array_equal(np.array(ranges), np.stack([offsets[:-1], offsets[1:]], 1))
    assert (tiles_x, tiles_y) == (4, 3)


def test_mlx_binning_never_calls_the_compiled_module(monkeypatch):
    def missing():
        raise ExtensionBuildError("mlx3d._core is missing")

    monkeypatch.setattr(native, "core", missing)
    rng = np.random.default_rng(6)
    means2d, radii, depths = random_scene(rng, 200, 40, 30)
    conics, _, opac = random_conics(rng, 200)
    bins = bin_tiles(means2d, radii, depths, 40, 30, 8, conics, opac, backend="mlx")
    assert bins.flatten_ids.size > 0
    bin_gaussians(means2d, radii, depths, 40, 30, conics, opacities=opac, backend="mlx")
    tile_extents(radii, conics, opac, backend="mlx")
    with pytest.raises(ExtensionBuildError):
        bin_tiles(means2d, radii, depths, 40, 30, backend="cpu")
