"""Tile binning against a brute-force construction of the same lists."""

import numpy as np
import pytest

import mlx.core as mx

from mlx3d.render import bin_tiles
from mlx3d.render.binning import tile_extents
from mlx3d.render.raster_cpu import rasterize_cpu


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


@pytest.mark.parametrize("seed, width, height, tile", [(0, 40, 30, 16), (1, 64, 64, 16), (2, 33, 17, 8)])
def test_bins_match_brute_force(seed, width, height, tile):
    rng = np.random.default_rng(seed)
    n = 150
    means2d = rng.uniform(-20, width + 20, (n, 2))
    radii = rng.integers(0, 25, n)
    depths = rng.uniform(0.1, 10, n)
    depths[:10] = depths[10]  # ties sort by Gaussian index
    bins = bin_tiles(means2d, radii, depths, width, height, tile)
    offsets, ids = brute_bins(means2d, radii, depths, width, height, tile)
    np.testing.assert_array_equal(np.array(bins.tile_offsets), offsets)
    np.testing.assert_array_equal(np.array(bins.flatten_ids), ids)
    assert (bins.tiles_x, bins.tiles_y) == (-(-width // tile), -(-height // tile))


def test_threaded_binning_matches_a_numpy_oracle_for_any_thread_count():
    # enough Gaussians that every thread gets a chunk (16,384 at least each), with depth ties and culled ones
    from thread_counts import per_thread_count

    rng = np.random.default_rng(5)
    n, width, height, tile = 70_000, 320, 200, 16
    means2d = rng.uniform(-10, [width + 10, height + 10], (n, 2))
    radii = rng.integers(0, 20, n)
    depths = np.round(rng.uniform(0.1, 5, n), 2)  # many ties: they sort by index
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    lo = np.clip(np.floor((means2d - radii[:, None]) / tile), 0, [tiles_x, tiles_y]).astype(int)
    hi = np.clip(np.floor((means2d + radii[:, None]) / tile) + 1, 0, [tiles_x, tiles_y]).astype(int)
    tile_ids, keys, gauss = [], [], []
    for dy in range(4):
        for dx in range(4):
            tx, ty = lo[:, 0] + dx, lo[:, 1] + dy
            hit = (radii > 0) & (tx < hi[:, 0]) & (ty < hi[:, 1])
            tile_ids.append((ty * tiles_x + tx)[hit])
            keys.append(depths.astype(np.float32)[hit])
            gauss.append(np.flatnonzero(hit))
    assert (hi - lo).max() <= 4  # every tile covered
    tile_ids, keys, gauss = (np.concatenate(a) for a in (tile_ids, keys, gauss))
    order = np.lexsort((gauss, keys, tile_ids))
    offsets = np.searchsorted(tile_ids[order], np.arange(tiles_x * tiles_y + 1))
    results = per_thread_count(lambda: bin_tiles(means2d, radii, depths, width, height, tile), (1, 2, 3, 5))
    for bins in results:
        np.testing.assert_array_equal(np.array(bins.tile_offsets), offsets)
        np.testing.assert_array_equal(np.array(bins.flatten_ids), gauss[order])


def test_empty_and_all_culled():
    bins = bin_tiles(np.zeros((5, 2)), np.zeros(5), np.ones(5), 40, 30)
    assert np.array(bins.tile_offsets).tolist() == [0] * 7 and bins.flatten_ids.size == 0
    bins = bin_tiles(np.zeros((0, 2)), np.zeros(0), np.zeros(0), 40, 30)
    assert bins.flatten_ids.size == 0


def test_bad_tile_size():
    with pytest.raises(ValueError, match="tile_size"):
        bin_tiles(np.zeros((1, 2)), np.ones(1), np.ones(1), 8, 8, tile_size=0)


def test_extents_match_the_formula_in_numpy():
    """The C++ half-extents against the module docstring's formula in float64 numpy, bit for bit after
    rounding to float32, over random conics with the edge cases: det <= 0, 255 o <= 1, r = 0, r binding."""
    rng = np.random.default_rng(11)
    n = 20_000
    radii = rng.integers(0, 40, n).astype(np.float32)
    conics = np.stack([rng.uniform(1e-4, 2, n), rng.uniform(-1, 1, n), rng.uniform(1e-4, 2, n)], 1).astype(np.float32)
    opac = rng.uniform(0, 1, n).astype(np.float32)
    opac[:50] = 1 / 255  # reaches nothing
    r, con, o = radii.astype(np.float64), conics.astype(np.float64), opac.astype(np.float64)
    det = con[:, 0] * con[:, 2] - con[:, 1] ** 2
    k = 2.0 * np.log(np.maximum(255.0 * o, 1e-30))
    live = (r > 0) & (det > 0) & (k > 0)
    inv = np.where(live, 1.0 / np.where(live, det, 1.0), 0.0)
    ext = np.minimum(np.sqrt(np.maximum(k, 0.0)[:, None] * np.stack([con[:, 2] * inv, con[:, 0] * inv], axis=1)) + 1.0, r[:, None])
    want = np.where(live[:, None], ext, 0.0).astype(np.float32)
    assert (~live).sum() > 1000 and (ext[live] == r[live, None]).any() and (ext[live] < r[live, None]).any()
    np.testing.assert_array_equal(tile_extents(radii, conics, opac), want)
    np.testing.assert_array_equal(tile_extents(radii), np.stack([radii, radii], 1))


def test_opacity_aware_extents_change_no_pixel():
    """Tighter tile extents drop only entries every pixel would skip: identical images, fewer entries."""
    rng = np.random.default_rng(3)
    n, width, height = 400, 96, 80
    means2d = mx.array(rng.uniform(0, 96, (n, 2)).astype(np.float32))
    # random anisotropic covariances, some faint Gaussians (255·o <= 1 reaches no tile)
    angle = rng.uniform(0, np.pi, n)
    s1, s2 = rng.uniform(1, 12, n), rng.uniform(0.5, 3, n)
    c, s_ = np.cos(angle), np.sin(angle)
    cov = np.stack([c * c * s1**2 + s_ * s_ * s2**2, c * s_ * (s1**2 - s2**2), s_ * s_ * s1**2 + c * c * s2**2], 1) + [0.3, 0, 0.3]
    det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
    conics = mx.array(np.stack([cov[:, 2], -cov[:, 1], cov[:, 0]], 1).astype(np.float32) / det[:, None].astype(np.float32))
    lam = 0.5 * (cov[:, 0] + cov[:, 2]) + np.sqrt(np.maximum(0.25 * (cov[:, 0] - cov[:, 2]) ** 2 + cov[:, 1] ** 2, 0.1))
    radii = np.ceil(3 * np.sqrt(lam))
    opac = rng.uniform(0.001, 0.99, n).astype(np.float32)
    opac[:20] = 0.003
    depths = rng.uniform(1, 5, n)
    colors = mx.array(rng.uniform(0, 1, (n, 3)).astype(np.float32))
    loose = bin_tiles(means2d, radii, depths, width, height)
    tight = bin_tiles(means2d, radii, depths, width, height, conics=conics, opacities=opac)
    assert tight.flatten_ids.size < loose.flatten_ids.size
    assert not np.isin(np.arange(20), np.array(tight.flatten_ids)).any()
    a = rasterize_cpu(means2d, conics, colors, mx.array(opac), loose.tile_offsets, loose.flatten_ids, width, height)
    b = rasterize_cpu(means2d, conics, colors, mx.array(opac), tight.tile_offsets, tight.flatten_ids, width, height)
    np.testing.assert_array_equal(np.array(a[0]), np.array(b[0]))
    np.testing.assert_array_equal(np.array(a[1]), np.array(b[1]))
    ext = tile_extents(radii, conics, opac)
    assert (ext <= radii[:, None] + 1e-6).all()
