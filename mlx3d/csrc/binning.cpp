// Tile binning on numpy arrays: the kernel library's mlx3d_bin_tiles and mlx3d_tile_extents (kernels/binning.cpp,
// mlx3d_kernels.h), whose outputs become MLX arrays without a copy.

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/pair.h>

#include <algorithm>
#include <cstdint>
#include <optional>
#include <stdexcept>

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

// radii (N,), with conics (N,3) and opacities (N,) or neither (the half-extents of kernels/binning.cpp).
void check_extent_inputs(const Vec1& radii, const std::optional<Vec3>& conics, const std::optional<Vec1>& opacities, int64_t n) {
  if (static_cast<int64_t>(radii.shape(0)) != n) throw nb::value_error("bin_tiles: radii must have one entry per Gaussian");
  if (conics.has_value() != opacities.has_value()) throw nb::value_error("bin_tiles: give conics and opacities together, or neither");
  if (conics && (static_cast<int64_t>(conics->shape(0)) != n || static_cast<int64_t>(opacities->shape(0)) != n))
    throw nb::value_error("bin_tiles: conics and opacities must have one row per Gaussian");
}

std::pair<mx::array, mx::array> bin_tiles(const Vec2& means2d, const Vec1& radii, const Vec1& depths, int width, int height, int tile_size,
                                          int num_threads, const std::optional<Vec3>& conics, const std::optional<Vec1>& opacities) {
  const int64_t n = static_cast<int64_t>(means2d.shape(0));
  if (static_cast<int64_t>(depths.shape(0)) != n) throw nb::value_error("bin_tiles: means2d and depths must have the same number of rows");
  check_extent_inputs(radii, conics, opacities, n);
  if (width < 1 || height < 1 || tile_size < 1) throw nb::value_error("bin_tiles: width, height and tile_size must be >= 1");
  const int64_t num_tiles = int64_t((width + tile_size - 1) / tile_size) * ((height + tile_size - 1) / tile_size);
  HugePageArray<int32_t> offsets(num_tiles + 1);
  int32_t* ids = nullptr;
  int64_t total = 0;
  int rc;
  {
    nb::gil_scoped_release release;
    rc = mlx3d_bin_tiles(means2d.data(), radii.data(), depths.data(), n, width, height, tile_size, conics ? conics->data() : nullptr,
                         opacities ? opacities->data() : nullptr, num_threads, offsets.data(), &ids, &total);
  }
  if (rc == 1) throw std::overflow_error(mlx3d_last_error());  // more entries than int32 indices reach
  check_call(rc);
  // MLX int32 vectors that take over the blocks without a copy (the 38M entries of a 1M-Gaussian frame took
  // ~90 ms to copy).
  const mx::array ids_array = total == 0 ? mx::array({}, mx::int32)
                                         : mx::array(ids, mx::Shape{static_cast<int32_t>(total)}, mx::int32, [](void* p) { mlx3d_free(p); });
  return {mx::array(offsets.release(), mx::Shape{static_cast<int32_t>(num_tiles + 1)}, mx::int32, [](void* p) { aligned_free(p); }),
          ids_array};
}

// The half-extents of every Gaussian, (N,2) float32 (as bin_tiles uses them; for tests and tools).
nb::ndarray<nb::numpy, float, nb::shape<-1, 2>> tile_extents(const Vec1& radii, const std::optional<Vec3>& conics,
                                                             const std::optional<Vec1>& opacities) {
  const int64_t n = static_cast<int64_t>(radii.shape(0));
  check_extent_inputs(radii, conics, opacities, n);
  float* out = new float[std::max<int64_t>(2 * n, 1)];
  nb::capsule owner(out, [](void* p) noexcept { delete[] static_cast<float*>(p); });
  check_call(mlx3d_tile_extents(radii.data(), conics ? conics->data() : nullptr, opacities ? opacities->data() : nullptr, n, out));
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
