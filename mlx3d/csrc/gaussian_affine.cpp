// Gaussian covariances re-decomposed under a linear map (mlx3d.transforms.transform_gaussians): the kernel
// library's mlx3d_affine_covariances (kernels/affine.cpp, mlx3d_kernels.h) on numpy arrays, with the GIL
// released.
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

using Lin = nb::ndarray<const double, nb::shape<3, 3>, nb::c_contig, nb::device::cpu>;
using Quats = nb::ndarray<const float, nb::shape<-1, 4>, nb::c_contig, nb::device::cpu>;
using Scales = nb::ndarray<const float, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;
using QuatsOut = nb::ndarray<float, nb::shape<-1, 4>, nb::c_contig, nb::device::cpu>;
using ScalesOut = nb::ndarray<float, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;

void affine_covariances(const Lin& linear, const Quats& quats, const Scales& log_scales, QuatsOut quats_out,
                        ScalesOut log_scales_out, int num_threads) {
  const int64_t n = static_cast<int64_t>(quats.shape(0));
  if (static_cast<int64_t>(log_scales.shape(0)) != n || static_cast<int64_t>(quats_out.shape(0)) != n ||
      static_cast<int64_t>(log_scales_out.shape(0)) != n)
    throw nb::value_error("affine_covariances: quats, log_scales and outputs must have the same number of rows");
  int rc;
  {
    nb::gil_scoped_release release;
    rc = mlx3d_affine_covariances(linear.data(), quats.data(), log_scales.data(), n, num_threads, quats_out.data(), log_scales_out.data());
  }
  check_call(rc);
}

}  // namespace

void bind_gaussian_affine(nb::module_& m) {
  m.def("affine_covariances", &affine_covariances, "linear"_a, "quats"_a, "log_scales"_a, "quats_out"_a.noconvert(),
        "log_scales_out"_a.noconvert(), "num_threads"_a = 0,
        "Covariances R diag(s)² Rᵀ of (N,4) quats and (N,3) log scales mapped by a 3x3 float64 linear\n"
        "map L (L Σ Lᵀ), re-decomposed into unit quaternions and descending log scales written to\n"
        "the float32 outputs. Threaded; releases the GIL.");
}

}  // namespace mlx3d
