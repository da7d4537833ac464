// The densification statistics of one view, added in place (mlx3d.training.trainer's
// add_screen_statistics): the kernel library's mlx3d_add_screen_statistics (kernels/statistics.cpp) on
// the statistics' numpy arrays.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <cstdint>
#include <stdexcept>

#include "bindings.h"
#include "kernel_call.h"

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
  static_assert(sizeof(bool) == 1, "visible is read as one byte per Gaussian");
  int rc;
  {
    nb::gil_scoped_release release;
    rc = mlx3d_add_screen_statistics(reinterpret_cast<const uint8_t*>(visible.data()), grad2d.data(), radii.data(), n, sx, sy,
                                     grad_accum.data(), grad_count.data(), max_radii.data(), num_threads);
  }
  check_call(rc);
}

}  // namespace

void bind_screen_statistics(nb::module_& m) {
  m.def("add_screen_statistics", &add_screen_statistics, "visible"_a, "grad2d"_a, "radii"_a, "sx"_a, "sy"_a, "grad_accum"_a.noconvert(),
        "grad_count"_a.noconvert(), "max_radii"_a.noconvert(), "num_threads"_a = 0,
        "Adds one view to the float64 (N,) densification statistics in place: grad_accum += |grad2d * (sx, sy)| where\n"
        "visible (bool (N,)), grad_count += visible, max_radii = max(max_radii, radii (int32 (N,))); grad2d float32 (N,2).");
}

}  // namespace mlx3d
