// Entry point of the compiled module `mlx3d._core`.
//
// Built with NB_DOMAIN mlx so that `mlx.core.array` objects cross into this
// module as `mlx::core::array` (shared nanobind type registry with mlx.core).
#include <nanobind/nanobind.h>
#include <nanobind/stl/string.h>

#include <string>

#include "bindings.h"
#include "mlx/array.h"
#include "mlx/ops.h"
#include "mlx/version.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

NB_MODULE(_core, m) {
  m.doc() = "Compiled kernels of mlx3d (k-nearest neighbours, Gaussian affine maps, the MLX primitives of the projection, SH colour, rasterizer, training loss, Adam, the parameter activations and the densification statistics).";

  // mlx.core registers the array type; import it first so that the shared
  // "mlx" domain knows it before any function here is called.
  nb::module_::import_("mlx.core");

  m.def(
      "mlx_version", []() { return std::string(mx::version()); },
      "Version of the MLX library this module is linked against.");

  m.def(
      "_mlx_scale", [](const mx::array& a, float s) { return mx::multiply(a, mx::array(s)); },
      "a"_a, "s"_a,
      "Returns a * s as an mx.array (checks the MLX linkage and array interop).");

  mlx3d::bind_knn(m);
  mlx3d::bind_gaussian_affine(m);
  mlx3d::bind_binning(m);
  mlx3d::bind_rasterize(m);
  mlx3d::bind_sh_color(m);
  mlx3d::bind_adam(m);
  mlx3d::bind_projection(m);
  mlx3d::bind_photometric(m);
  mlx3d::bind_activation(m);
  mlx3d::bind_screen_statistics(m);
}
