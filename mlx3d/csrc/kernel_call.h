// A kernel library call's result (kernels/mlx3d_kernels.h: 0, 2 for an invalid argument, 1 for another failure,
// the message in mlx3d_last_error) as an exception (std::invalid_argument: Python's ValueError), for the
// module's primitives and bindings that run the library's kernels.
#pragma once

#include <stdexcept>

#include "kernels/mlx3d_kernels.h"

namespace mlx3d {

inline void check_call(int rc) {
  if (rc == 2) throw std::invalid_argument(mlx3d_last_error());
  if (rc != 0) throw std::runtime_error(mlx3d_last_error());
}

}  // namespace mlx3d
