// EWA projection of 3D Gaussians, threaded over Gaussians: mlx3d_project_ewa and mlx3d_project_ewa_backward
// (mlx3d_kernels.h).
//
// Forward: means (N,3), quats (N,4), scales (N,3) -> means2d (N,2), conics (N,3), radii (N,) int32, depths
// (N,), compensation (N,). Backward: the gradients of means, quats and scales from those of means2d, conics,
// depths and compensation (radii have none). The per-Gaussian math is projection_math.h (shared with Metal);
// each Gaussian is computed by one thread from its own inputs, several at a time (one per vector lane, each
// lane the float operations of one Gaussian alone), so results are bitwise identical for any thread count. The
// pure-MLX reference is mlx3d.render.projection.project_ewa(backend='reference').
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

// Lane-wise sqrt and ceil for projection_math.h (declared before it, as its templates look them up);
// both correctly rounded in every variant, and the file is built without FMA contraction, so the
// results do not depend on the lanes.
#if defined(MLX3D_VECTOR_LANES)
MLX3D_LANES_INLINE mlx3d::Lanes pm_sqrt(mlx3d::Lanes x) {
  for (int j = 0; j < mlx3d::kLanes; ++j) x[j] = __builtin_sqrtf(x[j]);
  return x;
}
MLX3D_LANES_INLINE mlx3d::Lanes pm_ceil(mlx3d::Lanes x) {
  for (int j = 0; j < mlx3d::kLanes; ++j) x[j] = __builtin_ceilf(x[j]);
  return x;
}
#endif
#include "../projection_math.h"

namespace mlx3d {
namespace {

constexpr int kBlock = 4096;  // at least this many Gaussians per thread

// Field f of `width` floats per Gaussian, of Gaussians [i0, i0 + count) and the last one repeated, as lanes.
MLX3D_LANES_INLINE Lanes gather(const float* a, int width, int f, int64_t i0, int count) {
  alignas(32) float t[kLanes];
  for (int j = 0; j < kLanes; ++j) t[j] = a[(i0 + std::min(j, count - 1)) * width + f];
  return lanes_at(t);
}

// Writes the first `count` lanes of v to field f of Gaussians [i0, i0 + count).
MLX3D_LANES_INLINE void scatter(float* a, int width, int f, int64_t i0, int count, Lanes v) {
  alignas(32) float t[kLanes];
  put_lanes(t, v);
  for (int j = 0; j < count; ++j) a[(i0 + j) * width + f] = t[j];
}

MLX3D_LANES_INLINE PmGaussianOf<Lanes> gaussians_at(const float* means, const float* quats, const float* scales, int64_t i0, int count) {
  PmGaussianOf<Lanes> g;
  for (int k = 0; k < 3; ++k) g.mean[k] = gather(means, 3, k, i0, count), g.scale[k] = gather(scales, 3, k, i0, count);
  for (int k = 0; k < 4; ++k) g.quat[k] = gather(quats, 4, k, i0, count);
  return g;
}

struct ForwardArrays {
  const float *means, *quats, *scales;
  float *means2d, *conics, *depths, *compensation;
  int32_t* radii;
};

struct BackwardArrays {
  const float *means, *quats, *scales;
  const float *d_means2d, *d_conics, *d_depths, *d_compensation;  // (N,2), (N,3), (N,), (N,)
  float *d_means, *d_quats, *d_scales;
};

MLX3D_AVX2_CLONES void forward_range(const PmCamera& cam, const ForwardArrays& a, int64_t lo, int64_t hi) {
  for (int64_t i0 = lo; i0 < hi; i0 += kLanes) {
    const int count = static_cast<int>(std::min<int64_t>(kLanes, hi - i0));
    const PmStateOf<Lanes> s = pm_forward(cam, gaussians_at(a.means, a.quats, a.scales, i0, count));
    for (int k = 0; k < 2; ++k) scatter(a.means2d, 2, k, i0, count, s.means2d[k]);
    for (int k = 0; k < 3; ++k) scatter(a.conics, 3, k, i0, count, s.conic[k]);
    scatter(a.depths, 1, 0, i0, count, s.depth);
    scatter(a.compensation, 1, 0, i0, count, s.compensation);
    alignas(32) float radius[kLanes];
    put_lanes(radius, s.radius);
    for (int j = 0; j < count; ++j) a.radii[i0 + j] = static_cast<int32_t>(radius[j]);
  }
}

MLX3D_AVX2_CLONES void backward_range(const PmCamera& cam, const BackwardArrays& a, int64_t lo, int64_t hi) {
  for (int64_t i0 = lo; i0 < hi; i0 += kLanes) {
    const int count = static_cast<int>(std::min<int64_t>(kLanes, hi - i0));
    const PmGaussianOf<Lanes> g = gaussians_at(a.means, a.quats, a.scales, i0, count);
    const PmStateOf<Lanes> s = pm_forward(cam, g);
    const PmGradOf<Lanes> d = pm_backward(cam, g, s, gather(a.d_means2d, 2, 0, i0, count), gather(a.d_means2d, 2, 1, i0, count),
                                          gather(a.d_conics, 3, 0, i0, count), gather(a.d_conics, 3, 1, i0, count),
                                          gather(a.d_conics, 3, 2, i0, count), gather(a.d_depths, 1, 0, i0, count),
                                          gather(a.d_compensation, 1, 0, i0, count));
    for (int k = 0; k < 3; ++k) scatter(a.d_means, 3, k, i0, count, d.mean[k]), scatter(a.d_scales, 3, k, i0, count, d.scale[k]);
    for (int k = 0; k < 4; ++k) scatter(a.d_quats, 4, k, i0, count, d.quat[k]);
  }
}

PmCamera make_camera(const float* viewmat, float fx, float fy, float cx, float cy, int width, int height, float near_z,
                     float far_z, float blur, int antialias) {
  require(viewmat != nullptr, "viewmat is a null pointer");
  require(width >= 1 && height >= 1, "width and height must be >= 1, got " + std::to_string(width) + " x " + std::to_string(height));
  PmCamera cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.rot[3 * i + j] = viewmat[4 * i + j];
    cam.trans[i] = viewmat[4 * i + 3];
  }
  cam.fx = fx, cam.fy = fy, cam.cx = cx, cam.cy = cy;
  cam.width = float(width), cam.height = float(height), cam.near_z = near_z, cam.far_z = far_z, cam.blur = blur;
  cam.antialias = antialias ? 1 : 0;
  return cam;
}

void check_counts(int64_t n, int threads) {
  require(n >= 0, "the count of Gaussians must be >= 0, got " + std::to_string(n));
  require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
}

}  // namespace
}  // namespace mlx3d

using namespace mlx3d;

extern "C" MLX3D_API int mlx3d_project_ewa(const float* means, const float* quats, const float* scales, int64_t n, const float* viewmat,
                                           float fx, float fy, float cx, float cy, int width, int height, float near_z, float far_z,
                                           float blur, int antialias, int threads, float* means2d, float* conics, int32_t* radii,
                                           float* depths, float* compensation) {
  return guarded("mlx3d_project_ewa", [&] {
    check_counts(n, threads);
    const PmCamera cam = make_camera(viewmat, fx, fy, cx, cy, width, height, near_z, far_z, blur, antialias);
    require(n == 0 || (means && quats && scales && means2d && conics && radii && depths && compensation), "a null pointer");
    const ForwardArrays a{means, quats, scales, means2d, conics, depths, compensation, radii};
    parallel_blocks(n, threads, kBlock, [a, cam](int64_t lo, int64_t hi) { forward_range(cam, a, lo, hi); });
  });
}

extern "C" MLX3D_API int mlx3d_project_ewa_backward(const float* means, const float* quats, const float* scales, int64_t n,
                                                    const float* viewmat, float fx, float fy, float cx, float cy, int width,
                                                    int height, float near_z, float far_z, float blur, int antialias,
                                                    const float* d_means2d, const float* d_conics, const float* d_depths,
                                                    const float* d_compensation, int threads, float* d_means, float* d_quats,
                                                    float* d_scales) {
  return guarded("mlx3d_project_ewa_backward", [&] {
    check_counts(n, threads);
    const PmCamera cam = make_camera(viewmat, fx, fy, cx, cy, width, height, near_z, far_z, blur, antialias);
    require(n == 0 || (means && quats && scales && d_means2d && d_conics && d_depths && d_compensation && d_means && d_quats &&
                       d_scales), "a null pointer");
    const BackwardArrays a{means, quats, scales, d_means2d, d_conics, d_depths, d_compensation, d_means, d_quats, d_scales};
    parallel_blocks(n, threads, kBlock, [a, cam](int64_t lo, int64_t hi) { backward_range(cam, a, lo, hi); });
  });
}
