// The densification statistics of one view, added in place: mlx3d_add_screen_statistics (mlx3d_kernels.h),
// threaded over the Gaussians:
//
//   grad_accum[i] += visible[i] ? |(gx sx, gy sy)| : 0;  grad_count[i] += visible[i];
//   max_radii[i] = max(max_radii[i], radii[i])
//
// with (gx, gy) = dL/d(means2d) in pixels and (sx, sy) = (W/2, H/2), which takes it to NDC units (as
// 3DGS's threshold expects). In float64, each operation rounded as numpy's whole-array expression it
// replaces (no contraction), so the statistics, and the densification that reads them, are the same bits;
// max as np.maximum (NaN wins).
#include <cmath>
#include <cstdint>
#include <string>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

extern "C" MLX3D_API int mlx3d_add_screen_statistics(const uint8_t* visible, const float* grad2d, const int32_t* radii, int64_t n,
                                                     double sx, double sy, double* grad_accum, double* grad_count, double* max_radii,
                                                     int threads) {
  return mlx3d::guarded("mlx3d_add_screen_statistics", [&] {
    mlx3d::require(n >= 0, "the count of Gaussians must be >= 0, got " + std::to_string(n));
    mlx3d::require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
    mlx3d::require(n == 0 || (visible && grad2d && radii && grad_accum && grad_count && max_radii), "a null pointer");
    const uint8_t* vis = visible;
    const float* g = grad2d;
    const int32_t* r = radii;
    double *acc = grad_accum, *count = grad_count, *radius = max_radii;
    mlx3d::parallel_blocks(n, threads, 16384, [=](int64_t lo, int64_t hi) {
      for (int64_t i = lo; i < hi; ++i) {
        const double x = double(g[2 * i]) * sx, y = double(g[2 * i + 1]) * sy;
        const double xx = x * x, yy = y * y;
        acc[i] += vis[i] ? std::sqrt(xx + yy) : 0.0;
        count[i] += vis[i] ? 1.0 : 0.0;
        const double a = radius[i], b = r[i];
        radius[i] = (a >= b || std::isnan(a)) ? a : b;
      }
    });
  });
}
