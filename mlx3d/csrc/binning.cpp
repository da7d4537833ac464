// Tile binning: (Gaussian, tile) intersections sorted by tile, then depth, then index.
//
// A Gaussian with half-extents (ex, ey) > 0 pixels around its mean covers the tiles
// floor((m - e) / tile) .. floor((m + e) / tile) on each axis, clipped to the image.
// The Gaussians are sorted once by (depth, index) (depths as order-preserving integer
// keys, so NaN sorts last and -0 equals 0); filling each tile's bucket in that order
// leaves every bucket sorted by depth, then index, with no per-tile sort. The numpy
// construction in tests/test_render_binning.py is the oracle.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/pair.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

#include "bindings.h"
#include "mlx/array.h"
#include "primitive_util.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

using Vec2 = nb::ndarray<const float, nb::shape<-1, 2>, nb::c_contig, nb::device::cpu>;
using Vec1 = nb::ndarray<const float, nb::shape<-1>, nb::c_contig, nb::device::cpu>;

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

// An MLX int32 vector that takes over `data` (n entries, allocated with new[]) without a copy where the
// allocator can wrap it (MLX copies it otherwise): the 38M entries of a 1M-Gaussian frame took ~90 ms to copy.
mx::array to_mlx(std::unique_ptr<int32_t[]> data, int64_t n) {
  if (n == 0) return mx::array({}, mx::int32);
  int32_t* raw = data.release();
  return mx::array(raw, mx::Shape{static_cast<int32_t>(n)}, mx::int32, [](void* p) { delete[] static_cast<int32_t*>(p); });
}

// The tile rectangle of Gaussian i (empty when culled).
Rect tile_rect(const float* m, const float* e, int64_t i, int tile_size, int32_t tiles_x, int32_t tiles_y) {
  Rect r{0, 0, 0, 0};
  const double ex = e[2 * i], ey = e[2 * i + 1];
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

// Work layout (threaded; the result does not depend on the thread count): the depth-sorted Gaussians are cut
// into one contiguous chunk per thread. Each chunk counts its entries per tile; a tile's bucket then holds
// chunk 0's entries, then chunk 1's, ..., so chunk c starts writing tile t at offsets[t] + the counts of
// chunks before c, and every thread fills its own part of each bucket in sorted order.
std::pair<mx::array, mx::array> bin_tiles(const Vec2& means2d, const Vec2& extents, const Vec1& depths, int width, int height,
                                    int tile_size, int num_threads) {
  const int64_t n = static_cast<int64_t>(means2d.shape(0));
  if (static_cast<int64_t>(extents.shape(0)) != n || static_cast<int64_t>(depths.shape(0)) != n)
    throw nb::value_error("bin_tiles: means2d, extents and depths must have the same number of rows");
  if (width < 1 || height < 1 || tile_size < 1) throw nb::value_error("bin_tiles: width, height and tile_size must be >= 1");
  const int32_t tiles_x = (width + tile_size - 1) / tile_size, tiles_y = (height + tile_size - 1) / tile_size;
  const int64_t num_tiles = static_cast<int64_t>(tiles_x) * tiles_y;
  const float* m = means2d.data();
  const float* e = extents.data();
  const float* d = depths.data();
  std::unique_ptr<int32_t[]> offsets(new int32_t[num_tiles + 1]());
  std::unique_ptr<int32_t[]> ids;
  int64_t total = 0;
  {
    nb::gil_scoped_release release;
    constexpr int64_t kMinPerThread = 16384;
    std::vector<Rect> rects(n);
    parallel_ranges(n, num_threads, kMinPerThread, [&](int64_t a, int64_t b) {
      for (int64_t i = a; i < b; ++i) rects[i] = tile_rect(m, e, i, tile_size, tiles_x, tiles_y);
    });
    // Gaussians that touch a tile, by (depth key, index): unique 64-bit keys, so any sort is stable.
    std::vector<uint64_t> order;
    order.reserve(n);
    for (int64_t i = 0; i < n; ++i)
      if (rects[i].x1 > rects[i].x0 && rects[i].y1 > rects[i].y0) order.push_back((uint64_t(depth_key(d[i])) << 32) | uint64_t(i));
    const int64_t k = static_cast<int64_t>(order.size());
    const int chunks = resolve_threads(num_threads, static_cast<int>(std::max<int64_t>(1, (k + kMinPerThread - 1) / kMinPerThread)));
    const int64_t step = (k + chunks - 1) / std::max(chunks, 1);
    auto chunk_of = [&](int64_t a) { return static_cast<int>(step ? a / step : 0); };
    // Sort each chunk, then merge neighbours pairwise.
    parallel_ranges(k, chunks, kMinPerThread, [&](int64_t a, int64_t b) { std::sort(order.begin() + a, order.begin() + b); });
    for (int64_t width_ = step; width_ > 0 && width_ < k; width_ *= 2)
      for (int64_t a = 0; a + width_ < k; a += 2 * width_)
        std::inplace_merge(order.begin() + a, order.begin() + a + width_, order.begin() + std::min(k, a + 2 * width_));
    // Entries per (chunk, tile), then each chunk's first slot in each bucket.
    std::vector<int64_t> counts(static_cast<size_t>(chunks) * num_tiles, 0);
    parallel_ranges(k, chunks, kMinPerThread, [&](int64_t a, int64_t b) {
      int64_t* c = &counts[static_cast<size_t>(chunk_of(a)) * num_tiles];
      for (int64_t j = a; j < b; ++j) for_each_tile(rects[order[j] & 0xffffffffu], tiles_x, [&](int64_t t) { ++c[t]; });
    });
    for (int64_t t = 0; t < num_tiles; ++t) {
      offsets[t] = static_cast<int32_t>(std::min<int64_t>(total, INT32_MAX));
      for (int c = 0; c < chunks; ++c) {
        const int64_t here = counts[static_cast<size_t>(c) * num_tiles + t];
        counts[static_cast<size_t>(c) * num_tiles + t] = total;  // now: chunk c's first slot in tile t
        total += here;
      }
    }
    if (total > INT32_MAX) throw std::overflow_error("bin_tiles: more than 2^31 tile intersections");
    offsets[num_tiles] = static_cast<int32_t>(total);
    ids.reset(new int32_t[total]);  // not zeroed: every entry is written below, by the threads
    parallel_ranges(k, chunks, kMinPerThread, [&](int64_t a, int64_t b) {
      int64_t* cursor = &counts[static_cast<size_t>(chunk_of(a)) * num_tiles];
      for (int64_t j = a; j < b; ++j) {
        const int32_t i = static_cast<int32_t>(order[j] & 0xffffffffu);
        for_each_tile(rects[i], tiles_x, [&](int64_t t) { ids[cursor[t]++] = i; });
      }
    });
  }
  return {to_mlx(std::move(offsets), num_tiles + 1), to_mlx(std::move(ids), total)};
}

}  // namespace

void bind_binning(nb::module_& m) {
  m.def("bin_tiles", &bin_tiles, "means2d"_a, "extents"_a, "depths"_a, "width"_a, "height"_a, "tile_size"_a = 16, "num_threads"_a = 0,
        "Tile intersections of Gaussians with (N,2) half-extents in pixels (0 = culled): returns\n"
        "MLX arrays (tile_offsets int32 (tiles+1,), flatten_ids int32 (M,)) sorted by tile, depth, index; the same for any\n"
        "num_threads (0: all hardware threads).");
}

}  // namespace mlx3d
