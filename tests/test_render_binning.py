"""Tile binning against a brute-force construction of the same lists."""

import numpy as np
import pytest

from mlx3d.render import bin_gaussians


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
    bins = bin_gaussians(means2d, radii, depths, width, height, tile)
    offsets, ids = brute_bins(means2d, radii, depths, width, height, tile)
    np.testing.assert_array_equal(np.array(bins.tile_offsets), offsets)
    np.testing.assert_array_equal(np.array(bins.flatten_ids), ids)
    assert (bins.tiles_x, bins.tiles_y) == (-(-width // tile), -(-height // tile))


def test_empty_and_all_culled():
    bins = bin_gaussians(np.zeros((5, 2)), np.zeros(5), np.ones(5), 40, 30)
    assert np.array(bins.tile_offsets).tolist() == [0] * 7 and bins.flatten_ids.size == 0
    bins = bin_gaussians(np.zeros((0, 2)), np.zeros(0), np.zeros(0), 40, 30)
    assert bins.flatten_ids.size == 0


def test_bad_tile_size():
    with pytest.raises(ValueError, match="tile_size"):
        bin_gaussians(np.zeros((1, 2)), np.ones(1), np.ones(1), 8, 8, tile_size=0)
