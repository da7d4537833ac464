// Tile binning: (Gaussian, tile) intersections sorted by tile, then depth, then index: mlx3d_bin_tiles and
// mlx3d_tile_extents (mlx3d_kernels.h).
//
// A Gaussian with half-extents (ex, ey) > 0 pixels around its mean covers the tiles
// floor((m - e) / tile) .. floor((m + e) / tile) on each axis, clipped to the image.
// The Gaussians are sorted once by (depth, index) (depths as order-preserving integer
// keys, so NaN sorts last and -0 equals 0); filling each tile's bucket in that order
// leaves every bucket sorted by depth, then index, with no per-tile sort. The numpy
// construction in tests/test_render_binning.py is the oracle.
//
// Half-extents: the radius r on both axes, or, given the conic (a, b, c) and opacity o, the box of
// the ellipse where alpha can reach 1/255, d^T conic d <= 2 ln(255 o): sqrt(2 ln(255 o) Sxx) + 1 px
// (Sxx = c / det, Syy = a / det), never beyond r; 0 (no tile) when r <= 0, det <= 0 or 255 o <= 1.
// Computed in double and rounded to float32.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

namespace mlx3d {
namespace {

constexpr double kRoundingMargin = 1.0;  // pixels added to the ellipse's box

// Per-Gaussian inputs of the half-extents (conic and opacity null: the radius alone).
struct ExtentInputs {
  const float* radii;
  const float* conics;
  const float* opacities;
};

// The float32 half-extents (ex, ey) of Gaussian i (see the top of the file).
inline void tile_extent(const ExtentInputs& in, int64_t i, float& ex, float& ey) {
  const double r = in.radii[i];
  if (!in.conics) {
    ex = ey = static_cast<float>(r);
    return;
  }
  const double a = in.conics[3 * i], b = in.conics[3 * i + 1], c = in.conics[3 * i + 2];
  const double det = a * c - b * b;
  const double k = 2.0 * std::log(std::max(255.0 * double(in.opacities[i]), 1e-30));
  if (!(r > 0 && det > 0 && k > 0)) {
    ex = ey = 0.0f;
    return;
  }
  const double inv = 1.0 / det;
  ex = static_cast<float>(std::min(std::sqrt(k * (c * inv)) + kRoundingMargin, r));
  ey = static_cast<float>(std::min(std::sqrt(k * (a * inv)) + kRoundingMargin, r));
}

struct Rect {
  int32_t x0, x1, y0, y1;  // [x0, x1) x [y0, y1)
};

// An unsigned key with the order of the float depth (negative < -0 = 0 < positive < NaN).
uint32_t depth_key(float v) {
  if (v == 0.0f) v = 0.0f;  // -0 sorts with 0
  uint32_t bits;
  std::memcpy(&bits, &v, sizeof(bits));
  if (std::isnan(v)) return 0xffffffffu;
  return (bits & 0x80000000u) ? ~bits : (bits | 0x80000000u);
}

int32_t clamp_tile(double v, int32_t hi) {
  if (!(v > 0)) return 0;  // also NaN
  return v >= hi ? hi : static_cast<int32_t>(v);
}

// The tile rectangle of Gaussian i (empty when culled).
Rect tile_rect(const float* m, const ExtentInputs& in, int64_t i, int tile_size, int32_t tiles_x, int32_t tiles_y) {
  Rect r{0, 0, 0, 0};
  float fx, fy;
  tile_extent(in, i, fx, fy);
  const double ex = fx, ey = fy;
  if (ex > 0 && ey > 0) {
    const double mx = m[2 * i], my = m[2 * i + 1];
    r.x0 = clamp_tile(std::floor((mx - ex) / tile_size), tiles_x);
    r.x1 = clamp_tile(std::floor((mx + ex) / tile_size) + 1, tiles_x);
    r.y0 = clamp_tile(std::floor((my - ey) / tile_size), tiles_y);
    r.y1 = clamp_tile(std::floor((my + ey) / tile_size) + 1, tiles_y);
  }
  return r;
}

// Calls fn(tile) for every tile of r.
template <typename Fn>
inline void for_each_tile(const Rect& r, int32_t tiles_x, Fn&& fn) {
  for (int32_t ty = r.y0; ty < r.y1; ++ty)
    for (int32_t tx = r.x0; tx < r.x1; ++tx) fn(static_cast<int64_t>(ty) * tiles_x + tx);
}

// Sorts keys (depth key << 32 | index, listed in index order) into the order of the unique 64-bit keys: a
// stable LSD radix sort on the depth keys, 8 bits per pass (a pass whose digit all keys share is skipped),
// each pass threaded: every chunk counts its digits, then writes its keys in order after the earlier
// chunks' keys of the same digit (no merge of sorted chunks on one thread).
void sort_by_depth(std::vector<uint64_t>& keys, int chunks, int64_t min_per_thread) {
  const int64_t k = static_cast<int64_t>(keys.size());
  const RangeSplit split = split_ranges(k, chunks, min_per_thread);
  std::vector<uint64_t> other(k);
  std::vector<int64_t> counts(static_cast<size_t>(split.threads) * 256);
  for (int shift = 32; shift < 64; shift += 8) {
    std::fill(counts.begin(), counts.end(), 0);
    const uint64_t* src = keys.data();
    parallel_ranges(k, split.threads, min_per_thread, [&](int64_t a, int64_t b) {
      int64_t* c = &counts[static_cast<size_t>(split.index(a)) * 256];
      for (int64_t j = a; j < b; ++j) ++c[(src[j] >> shift) & 255];
    });
    int64_t total = 0;
    bool shared = false;  // one digit for all keys: the pass would not move them
    for (int d = 0; d < 256; ++d) {
      int64_t of_digit = 0;
      for (int c = 0; c < split.threads; ++c) {
        int64_t& slot = counts[static_cast<size_t>(c) * 256 + d];
        const int64_t here = slot;
        slot = total;  // now: chunk c's first position for digit d
        total += here;
        of_digit += here;
      }
      shared = shared || of_digit == k;
    }
    if (shared) continue;
    uint64_t* dst = other.data();
    parallel_ranges(k, split.threads, min_per_thread, [&](int64_t a, int64_t b) {
      int64_t* cursor = &counts[static_cast<size_t>(split.index(a)) * 256];
      for (int64_t j = a; j < b; ++j) dst[cursor[(src[j] >> shift) & 255]++] = src[j];
    });
    keys.swap(other);
  }
}

// Boundaries (chunks + 1 positions) that cut the depth-sorted rectangles rects[0, k) into contiguous
// chunks with about the same number of tile entries each (near Gaussians cover many tiles: equal counts of
// Gaussians left one core idle for much of the count and fill passes). Each rectangle covers >= 1 tile.
std::vector<int64_t> balanced_chunks(const Rect* rects, int64_t k, int chunks) {
  constexpr int64_t kBlock = 4096;  // rectangles whose entries are summed together before the walk
  auto entries = [&](int64_t j) { return int64_t(rects[j].x1 - rects[j].x0) * (rects[j].y1 - rects[j].y0); };
  const int blocks = static_cast<int>((k + kBlock - 1) / kBlock);
  std::vector<int64_t> block_entries(blocks, 0);
  parallel_items(0, blocks, chunks, [&](int blk, int) {
    int64_t sum = 0;
    for (int64_t j = blk * kBlock; j < std::min(k, (blk + 1) * kBlock); ++j) sum += entries(j);
    block_entries[blk] = sum;
  });
  int64_t total = 0;
  for (int64_t e : block_entries) total += e;
  std::vector<int64_t> bound(chunks + 1, k);
  bound[0] = 0;
  int c = 1;
  int64_t before = 0;  // entries of the blocks before blk
  for (int blk = 0; blk < blocks && c < chunks; before += block_entries[blk++]) {
    // chunk c starts after the rectangles whose entries, with all before them, stay within total * c / chunks
    for (int64_t target; c < chunks && (target = total * c / chunks) < before + block_entries[blk]; ++c) {
      int64_t j = blk * kBlock, sum = before;
      while (sum + entries(j) <= target) sum += entries(j++);
      bound[c] = j;
    }
  }
  return bound;
}

// Work layout (threaded; the result does not depend on the thread count): the depth-sorted Gaussians are cut
// into one contiguous chunk per thread, with about equal entries (balanced_chunks). Each chunk counts its
// entries per tile; a tile's bucket then holds chunk 0's entries, then chunk 1's, ..., so chunk c starts
// writing tile t at offsets[t] + the counts of chunks before c, and every thread fills its own part of each
// bucket in sorted order.
// Writes offsets (tiles + 1) and returns the entries (total of them), in a block for mlx3d_free.
int32_t* bin(const float* m, const ExtentInputs& ext, const float* d, int64_t n, int tile_size, int32_t tiles_x, int32_t tiles_y,
             int threads, int32_t* offsets, int64_t& total) {
  const int64_t num_tiles = static_cast<int64_t>(tiles_x) * tiles_y;
  total = 0;
  constexpr int64_t kMinPerThread = 16384;
  HugePageArray<Rect> rects(n);  // read in depth order: random
  parallel_blocks(n, threads, kMinPerThread, [&](int64_t a, int64_t b) {
    for (int64_t i = a; i < b; ++i) rects[i] = tile_rect(m, ext, i, tile_size, tiles_x, tiles_y);
  });
  // Gaussians that touch a tile, by (depth key, index): unique 64-bit keys, so any sort is stable. Listed
  // in index order by all threads at once: each counts its range's, then writes them from its offset.
  auto touches = [&](int64_t i) { return rects[i].x1 > rects[i].x0 && rects[i].y1 > rects[i].y0; };
  const RangeSplit listing = split_ranges(n, threads, kMinPerThread);
  std::vector<int64_t> first(listing.threads + 1, 0);
  parallel_ranges(n, listing.threads, kMinPerThread, [&](int64_t a, int64_t b) {
    int64_t live = 0;
    for (int64_t i = a; i < b; ++i) live += touches(i);
    if (a < b) first[listing.index(a) + 1] = live;
  });
  for (int t = 0; t < listing.threads; ++t) first[t + 1] += first[t];
  const int64_t k = first[listing.threads];
  std::vector<uint64_t> order(k);
  parallel_ranges(n, listing.threads, kMinPerThread, [&](int64_t a, int64_t b) {
    if (a == b) return;
    int64_t j = first[listing.index(a)];
    for (int64_t i = a; i < b; ++i)
      if (touches(i)) order[j++] = (uint64_t(depth_key(d[i])) << 32) | uint64_t(i);
  });
  const int chunks = split_ranges(k, threads, kMinPerThread).threads;
  sort_by_depth(order, chunks, kMinPerThread);
  // The rectangles in that order, gathered once, so that the two passes below read them in sequence.
  HugePageArray<Rect> sorted(k);
  parallel_blocks(k, chunks, kMinPerThread, [&](int64_t a, int64_t b) {
    for (int64_t j = a; j < b; ++j) sorted[j] = rects[order[j] & 0xffffffffu];
  });
  const std::vector<int64_t> bound = balanced_chunks(sorted.data(), k, chunks);
  // Entries per (chunk, tile), then each chunk's first slot in each bucket.
  std::vector<int64_t> counts(static_cast<size_t>(chunks) * num_tiles, 0);
  run_threads(chunks, [&](int c) {
    int64_t* count = &counts[static_cast<size_t>(c) * num_tiles];
    for (int64_t j = bound[c]; j < bound[c + 1]; ++j) for_each_tile(sorted[j], tiles_x, [&](int64_t t) { ++count[t]; });
  });
  for (int64_t t = 0; t < num_tiles; ++t) {
    offsets[t] = static_cast<int32_t>(std::min<int64_t>(total, INT32_MAX));
    for (int c = 0; c < chunks; ++c) {
      const int64_t here = counts[static_cast<size_t>(c) * num_tiles + t];
      counts[static_cast<size_t>(c) * num_tiles + t] = total;  // now: chunk c's first slot in tile t
      total += here;
    }
  }
  if (total > INT32_MAX) throw std::overflow_error("more than 2^31 tile intersections");
  offsets[num_tiles] = static_cast<int32_t>(total);
  HugePageArray<int32_t> ids(total);  // not zeroed: every entry is written below, by the threads; each
                                      // Gaussian writes to one bucket per tile: huge pages spare the TLB
  run_threads(chunks, [&](int c) {
    int64_t* cursor = &counts[static_cast<size_t>(c) * num_tiles];
    for (int64_t j = bound[c]; j < bound[c + 1]; ++j) {
      const int32_t i = static_cast<int32_t>(order[j] & 0xffffffffu);
      for_each_tile(sorted[j], tiles_x, [&](int64_t t) { ids[cursor[t]++] = i; });
    }
  });
  return ids.release();
}

void check_extent_inputs(const float* radii, const float* conics, const float* opacities, int64_t n) {
  require(n >= 0, "the count of Gaussians must be >= 0, got " + std::to_string(n));
  require(n == 0 || radii, "radii is a null pointer");
  require((conics == nullptr) == (opacities == nullptr), "give conics and opacities together, or neither");
}

}  // namespace
}  // namespace mlx3d

using namespace mlx3d;

extern "C" {

MLX3D_API int mlx3d_bin_tiles(const float* means2d, const float* radii, const float* depths, int64_t n, int width, int height,
                              int tile_size, const float* conics, const float* opacities, int threads, int32_t* tile_offsets,
                              int32_t** flatten_ids, int64_t* m) {
  return guarded("mlx3d_bin_tiles", [&] {
    check_extent_inputs(radii, conics, opacities, n);
    require(width >= 1 && height >= 1 && tile_size >= 1, "width, height and tile_size must be >= 1");
    require(n <= INT32_MAX, "more than 2^31 Gaussians");
    require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
    require(n == 0 || (means2d && depths), "means2d or depths is a null pointer");
    require(tile_offsets && flatten_ids && m, "an output is a null pointer");
    *flatten_ids = nullptr;
    *m = 0;
    const int32_t tiles_x = (width + tile_size - 1) / tile_size, tiles_y = (height + tile_size - 1) / tile_size;
    int64_t total = 0;
    int32_t* ids = bin(means2d, ExtentInputs{radii, conics, opacities}, depths, n, tile_size, tiles_x, tiles_y, threads,
                       tile_offsets, total);
    if (total == 0) {
      aligned_free(ids);
      ids = nullptr;
    }
    *flatten_ids = ids;
    *m = total;
  });
}

MLX3D_API int mlx3d_tile_extents(const float* radii, const float* conics, const float* opacities, int64_t n, float* extents) {
  return guarded("mlx3d_tile_extents", [&] {
    check_extent_inputs(radii, conics, opacities, n);
    require(n == 0 || extents, "extents is a null pointer");
    const ExtentInputs in{radii, conics, opacities};
    for (int64_t i = 0; i < n; ++i) tile_extent(in, i, extents[2 * i], extents[2 * i + 1]);
  });
}

MLX3D_API void mlx3d_free(void* block) { aligned_free(block); }

}  // extern "C"
