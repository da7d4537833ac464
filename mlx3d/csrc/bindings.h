// Registration functions of the parts of the `mlx3d._core` module.
#pragma once

#include <nanobind/nanobind.h>

namespace mlx3d {

void bind_knn(nanobind::module_& m);
void bind_gaussian_affine(nanobind::module_& m);
void bind_binning(nanobind::module_& m);
void bind_rasterize(nanobind::module_& m);
void bind_sh_color(nanobind::module_& m);
void bind_adam(nanobind::module_& m);
void bind_projection(nanobind::module_& m);
void bind_photometric(nanobind::module_& m);
void bind_activation(nanobind::module_& m);
void bind_screen_statistics(nanobind::module_& m);

}  // namespace mlx3d
