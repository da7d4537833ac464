// The densification statistics of one view, added in place (mlx3d.training.trainer's
// add_screen_statistics), threaded over the Gaussians:
//
//   grad_accum[i] += visible[i] ? |(gx sx, gy sy)| : 0;  grad_count[i] += visible[i];
//   max_radii[i] = max(max_radii[i], radii[i])
//
// with (gx, gy) = dL/d(means2d) in pixels and (sx, sy) = (W/2, H/2), which takes it to NDC units (as
// 3DGS's threshold expects). In float64, each operation rounded as numpy's whole-array expression it
// replaces (no contraction: CMakeLists.txt), so the statistics, and the densification that reads them,
// are the same bits; max as np.maximum (NaN wins).
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <cmath>
#include <cstdint>

#include "bindings.h"
#include "primitive_util.h"

namespace nb = nanobind;
using namespace nb::literals;

namespace mlx3d {
namespace {

template <class T>
using In = nb::ndarray<const T, nb::c_contig, nb::device::cpu>;
using Out = nb::ndarray<double, nb::shape<-1>, nb::c_contig, nb::device::cpu>;

void add_screen_statistics(const In<bool>& visible, const In<float>& grad2d, const In<int32_t>& radii, double sx, double sy,
                           Out grad_accum, Out grad_count, Out max_radii, int num_threads) {
  const int64_t n = static_cast<int64_t>(visible.size());
  if (grad2d.size() != size_t(2 * n) || radii.size() != size_t(n) || grad_accum.shape(0) != size_t(n) ||
      grad_count.shape(0) != size_t(n) || max_radii.shape(0) != size_t(n))
    throw nb::value_error("add_screen_statistics: visible (N,), grad2d (N,2), radii (N,) and the three (N,) statistics must agree on N");
  const bool* vis = visible.data();
  const float* g = grad2d.data();
  const int32_t* r = radii.data();
  double *acc = grad_accum.data(), *count = grad_count.data(), *radius = max_radii.data();
  nb::gil_scoped_release release;
  parallel_blocks(n, num_threads, 16384, [=](int64_t lo, int64_t hi) {
    for (int64_t i = lo; i < hi; ++i) {
      const double x = double(g[2 * i]) * sx, y = double(g[2 * i + 1]) * sy;
      const double xx = x * x, yy = y * y;
      acc[i] += vis[i] ? std::sqrt(xx + yy) : 0.0;
      count[i] += vis[i] ? 1.0 : 0.0;
      const double a = radius[i], b = r[i];
      radius[i] = (a >= b || std::isnan(a)) ? a : b;
    }
  });
}

}  // namespace

void bind_screen_statistics(nb::module_& m) {
  m.def("add_screen_statistics", &add_screen_statistics, "visible"_a, "grad2d"_a, "radii"_a, "sx"_a, "sy"_a, "grad_accum"_a,
        "grad_count"_a, "max_radii"_a, "num_threads"_a = 0,
        "Adds one view to the float64 (N,) densification statistics in place: grad_accum += |grad2d * (sx, sy)| where\n"
        "visible (bool (N,)), grad_count += visible, max_radii = max(max_radii, radii (int32 (N,))); grad2d float32 (N,2).");
}

}  // namespace mlx3d
