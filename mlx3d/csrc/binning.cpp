// Tile binning: (Gaussian, tile) intersections sorted by tile, then depth, then index.
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
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/pair.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <optional>
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
using Vec3 = nb::ndarray<const float, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;

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

// An MLX int32 vector that takes over `data` (n entries) without a copy where the allocator can wrap it
// (MLX copies it otherwise): the 38M entries of a 1M-Gaussian frame took ~90 ms to copy.
mx::array to_mlx(HugePageArray<int32_t> data, int64_t n) {
  if (n == 0) return mx::array({}, mx::int32);
  int32_t* raw = data.release();
  return mx::array(raw, mx::Shape{static_cast<int32_t>(n)}, mx::int32, [](void* p) { std::free(p); });
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

// Work layout (threaded; the result does not depend on the thread count): the depth-sorted Gaussians are cut
// into one contiguous chunk per thread. Each chunk counts its entries per tile; a tile's bucket then holds
// chunk 0's entries, then chunk 1's, ..., so chunk c starts writing tile t at offsets[t] + the counts of
// chunks before c, and every thread fills its own part of each bucket in sorted order.
// radii (N,), with conics (N,3) and opacities (N,) or neither: the half-extents above.
ExtentInputs extent_inputs(const Vec1& radii, const std::optional<Vec3>& conics, const std::optional<Vec1>& opacities, int64_t n) {
  if (static_cast<int64_t>(radii.shape(0)) != n) throw nb::value_error("bin_tiles: radii must have one entry per Gaussian");
  if (conics.has_value() != opacities.has_value()) throw nb::value_error("bin_tiles: give conics and opacities together, or neither");
  if (conics && (static_cast<int64_t>(conics->shape(0)) != n || static_cast<int64_t>(opacities->shape(0)) != n))
    throw nb::value_error("bin_tiles: conics and opacities must have one row per Gaussian");
  return {radii.data(), conics ? conics->data() : nullptr, opacities ? opacities->data() : nullptr};
}

std::pair<mx::array, mx::array> bin_tiles(const Vec2& means2d, const Vec1& radii, const Vec1& depths, int width, int height, int tile_size,
                                          int num_threads, const std::optional<Vec3>& conics, const std::optional<Vec1>& opacities) {
  const int64_t n = static_cast<int64_t>(means2d.shape(0));
  if (static_cast<int64_t>(depths.shape(0)) != n) throw nb::value_error("bin_tiles: means2d and depths must have the same number of rows");
  const ExtentInputs ext = extent_inputs(radii, conics, opacities, n);
  if (width < 1 || height < 1 || tile_size < 1) throw nb::value_error("bin_tiles: width, height and tile_size must be >= 1");
  const int32_t tiles_x = (width + tile_size - 1) / tile_size, tiles_y = (height + tile_size - 1) / tile_size;
  const int64_t num_tiles = static_cast<int64_t>(tiles_x) * tiles_y;
  const float* m = means2d.data();
  const float* d = depths.data();
  HugePageArray<int32_t> offsets(num_tiles + 1);
  HugePageArray<int32_t> ids(0);
  int64_t total = 0;
  {
    nb::gil_scoped_release release;
    constexpr int64_t kMinPerThread = 16384;
    HugePageArray<Rect> rects(n);  // read in depth order: random
    parallel_ranges(n, num_threads, kMinPerThread, [&](int64_t a, int64_t b) {
      for (int64_t i = a; i < b; ++i) rects[i] = tile_rect(m, ext, i, tile_size, tiles_x, tiles_y);
    });
    // Gaussians that touch a tile, by (depth key, index): unique 64-bit keys, so any sort is stable. Listed
    // in index order by all threads at once: each counts its range's, then writes them from its offset.
    auto touches = [&](int64_t i) { return rects[i].x1 > rects[i].x0 && rects[i].y1 > rects[i].y0; };
    const RangeSplit listing = split_ranges(n, num_threads, kMinPerThread);
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
    const RangeSplit split = split_ranges(k, num_threads, kMinPerThread);
    const int chunks = split.threads;
    // Sort each chunk, then merge neighbours pairwise.
    parallel_ranges(k, chunks, kMinPerThread, [&](int64_t a, int64_t b) { std::sort(order.begin() + a, order.begin() + b); });
    for (int64_t width_ = split.step; width_ > 0 && width_ < k; width_ *= 2)
      for (int64_t a = 0; a + width_ < k; a += 2 * width_)
        std::inplace_merge(order.begin() + a, order.begin() + a + width_, order.begin() + std::min(k, a + 2 * width_));
    // The rectangles in that order, gathered once, so that the two passes below read them in sequence.
    HugePageArray<Rect> sorted(k);
    parallel_ranges(k, chunks, kMinPerThread, [&](int64_t a, int64_t b) {
      for (int64_t j = a; j < b; ++j) sorted[j] = rects[order[j] & 0xffffffffu];
    });
    // Entries per (chunk, tile), then each chunk's first slot in each bucket.
    std::vector<int64_t> counts(static_cast<size_t>(chunks) * num_tiles, 0);
    parallel_ranges(k, chunks, kMinPerThread, [&](int64_t a, int64_t b) {
      int64_t* c = &counts[static_cast<size_t>(split.index(a)) * num_tiles];
      for (int64_t j = a; j < b; ++j) for_each_tile(sorted[j], tiles_x, [&](int64_t t) { ++c[t]; });
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
    ids = HugePageArray<int32_t>(total);  // not zeroed: every entry is written below, by the threads; each
                                          // Gaussian writes to one bucket per tile: huge pages spare the TLB
    parallel_ranges(k, chunks, kMinPerThread, [&](int64_t a, int64_t b) {
      int64_t* cursor = &counts[static_cast<size_t>(split.index(a)) * num_tiles];
      for (int64_t j = a; j < b; ++j) {
        const int32_t i = static_cast<int32_t>(order[j] & 0xffffffffu);
        for_each_tile(sorted[j], tiles_x, [&](int64_t t) { ids[cursor[t]++] = i; });
      }
    });
  }
  return {to_mlx(std::move(offsets), num_tiles + 1), to_mlx(std::move(ids), total)};
}

// The half-extents of every Gaussian, (N,2) float32 (as bin_tiles uses them; for tests and tools).
nb::ndarray<nb::numpy, float, nb::shape<-1, 2>> tile_extents(const Vec1& radii, const std::optional<Vec3>& conics,
                                                             const std::optional<Vec1>& opacities) {
  const int64_t n = static_cast<int64_t>(radii.shape(0));
  const ExtentInputs in = extent_inputs(radii, conics, opacities, n);
  float* out = new float[std::max<int64_t>(2 * n, 1)];
  nb::capsule owner(out, [](void* p) noexcept { delete[] static_cast<float*>(p); });
  for (int64_t i = 0; i < n; ++i) tile_extent(in, i, out[2 * i], out[2 * i + 1]);
  return nb::ndarray<nb::numpy, float, nb::shape<-1, 2>>(out, {static_cast<size_t>(n), 2}, owner);
}

}  // namespace

void bind_binning(nb::module_& m) {
  m.def("bin_tiles", &bin_tiles, "means2d"_a, "radii"_a, "depths"_a, "width"_a, "height"_a, "tile_size"_a = 16, "num_threads"_a = 0,
        "conics"_a = nb::none(), "opacities"_a = nb::none(),
        "Tile intersections of Gaussians (float32 means2d (N,2), radii (N,) with 0 = culled, depths (N,); with conics (N,3)\n"
        "and opacities (N,) the extents are tightened): returns MLX arrays (tile_offsets int32 (tiles+1,), flatten_ids\n"
        "int32 (M,)) sorted by tile, depth, index; the same for any num_threads (0: all hardware threads).");
  m.def("tile_extents", &tile_extents, "radii"_a, "conics"_a = nb::none(), "opacities"_a = nb::none(),
        "(N,2) float32 half-extents in pixels that bin_tiles gives each Gaussian.");
}

}  // namespace mlx3d
