// Gaussian covariances re-decomposed under a linear map, threaded over splats: mlx3d_affine_covariances
// (mlx3d_kernels.h).
//
// For each splat: M = L * R(q) * diag(exp(log_s)); the new covariance is M Mᵀ = U diag(σ)² Uᵀ. U and σ
// come from a one-sided Jacobi SVD of M (columns orthogonalised by plane rotations), which never forms
// M Mᵀ, so tiny scales keep their relative precision. U is made right-handed and returned as a unit
// quaternion (w,x,y,z, w >= 0); σ as log scales, sorted descending. All in double, each splat from its own
// inputs (results do not depend on the thread count); the numpy reference is
// mlx3d.transforms.transform_gaussians.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

namespace mlx3d {
namespace {

constexpr int64_t kBlock = 4096;  // at least this many splats per thread

using Mat3 = std::array<std::array<double, 3>, 3>;  // [row][col]

Mat3 quat_to_matrix(const float* q) {
  double w = q[0], x = q[1], y = q[2], z = q[3];
  double n = std::sqrt(w * w + x * x + y * y + z * z + 1e-24);
  w /= n, x /= n, y /= n, z /= n;
  return {{{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
           {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
           {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}}};
}

// Shepperd's method on a proper rotation matrix.
void matrix_to_quat(const Mat3& m, float* out) {
  double tr = m[0][0] + m[1][1] + m[2][2];
  double cand[4] = {1 + tr, 1 + m[0][0] - m[1][1] - m[2][2], 1 - m[0][0] + m[1][1] - m[2][2],
                    1 - m[0][0] - m[1][1] + m[2][2]};
  int best = static_cast<int>(std::max_element(cand, cand + 4) - cand);
  double q[4];
  switch (best) {
    case 0: q[0] = 1 + tr; q[1] = m[2][1] - m[1][2]; q[2] = m[0][2] - m[2][0]; q[3] = m[1][0] - m[0][1]; break;
    case 1: q[0] = m[2][1] - m[1][2]; q[1] = cand[1]; q[2] = m[0][1] + m[1][0]; q[3] = m[0][2] + m[2][0]; break;
    case 2: q[0] = m[0][2] - m[2][0]; q[1] = m[0][1] + m[1][0]; q[2] = cand[2]; q[3] = m[1][2] + m[2][1]; break;
    default: q[0] = m[1][0] - m[0][1]; q[1] = m[0][2] + m[2][0]; q[2] = m[1][2] + m[2][1]; q[3] = cand[3]; break;
  }
  double n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  double sign = q[0] < 0 ? -1.0 : 1.0;
  for (int i = 0; i < 4; ++i) out[i] = static_cast<float>(sign * q[i] / n);
}

void one_splat(const Mat3& lin, const float* q, const float* log_s, float* q_out, float* log_s_out) {
  Mat3 r = quat_to_matrix(q);
  Mat3 m{};
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      double acc = 0;
      for (int k = 0; k < 3; ++k) acc += lin[i][k] * r[k][j];
      m[i][j] = acc * std::exp(static_cast<double>(log_s[j]));
    }
  // One-sided Jacobi: rotate column pairs until they are orthogonal.
  for (int sweep = 0; sweep < 30; ++sweep) {
    bool rotated = false;
    for (int a = 0; a < 2; ++a)
      for (int b = a + 1; b < 3; ++b) {
        double alpha = 0, beta = 0, gamma = 0;
        for (int i = 0; i < 3; ++i) {
          alpha += m[i][a] * m[i][a];
          beta += m[i][b] * m[i][b];
          gamma += m[i][a] * m[i][b];
        }
        if (gamma == 0.0 || std::abs(gamma) <= 1e-15 * std::sqrt(alpha * beta)) continue;
        rotated = true;
        double zeta = (beta - alpha) / (2 * gamma);
        double t = (zeta >= 0 ? 1.0 : -1.0) / (std::abs(zeta) + std::sqrt(1 + zeta * zeta));
        double c = 1 / std::sqrt(1 + t * t), s = c * t;
        for (int i = 0; i < 3; ++i) {
          double ma = m[i][a], mb = m[i][b];
          m[i][a] = c * ma - s * mb;
          m[i][b] = s * ma + c * mb;
        }
      }
    if (!rotated) break;
  }
  std::array<double, 3> sigma;
  for (int j = 0; j < 3; ++j) sigma[j] = std::sqrt(m[0][j] * m[0][j] + m[1][j] * m[1][j] + m[2][j] * m[2][j]);
  std::array<int, 3> order = {0, 1, 2};
  std::sort(order.begin(), order.end(), [&](int x, int y) { return sigma[x] > sigma[y]; });
  Mat3 u{};  // columns: unit left singular vectors, descending sigma
  for (int c = 0; c < 3; ++c) {
    int j = order[c];
    for (int i = 0; i < 3; ++i) u[i][c] = sigma[j] > 0 ? m[i][j] / sigma[j] : 0.0;
  }
  // A vanished column (scale underflow) gets the direction orthogonal to the others.
  if (sigma[order[2]] <= 0) {
    u[0][2] = u[1][0] * u[2][1] - u[2][0] * u[1][1];
    u[1][2] = u[2][0] * u[0][1] - u[0][0] * u[2][1];
    u[2][2] = u[0][0] * u[1][1] - u[1][0] * u[0][1];
  }
  double det = u[0][0] * (u[1][1] * u[2][2] - u[1][2] * u[2][1]) - u[0][1] * (u[1][0] * u[2][2] - u[1][2] * u[2][0]) +
               u[0][2] * (u[1][0] * u[2][1] - u[1][1] * u[2][0]);
  if (det < 0)
    for (int i = 0; i < 3; ++i) u[i][2] = -u[i][2];
  matrix_to_quat(u, q_out);
  const double tiny = std::numeric_limits<double>::min();
  for (int c = 0; c < 3; ++c) log_s_out[c] = static_cast<float>(std::log(std::max(sigma[order[c]], tiny)));
}

}  // namespace
}  // namespace mlx3d

extern "C" MLX3D_API int mlx3d_affine_covariances(const double* linear, const float* quats, const float* log_scales, int64_t n,
                                                  int threads, float* quats_out, float* log_scales_out) {
  return mlx3d::guarded("mlx3d_affine_covariances", [&] {
    mlx3d::require(n >= 0, "the count of splats must be >= 0, got " + std::to_string(n));
    mlx3d::require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
    mlx3d::require(linear && (n == 0 || (quats && log_scales && quats_out && log_scales_out)), "a null pointer");
    mlx3d::Mat3 lin;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) lin[i][j] = linear[3 * i + j];
    const float *q = quats, *s = log_scales;
    float *qo = quats_out, *so = log_scales_out;
    mlx3d::parallel_blocks(n, threads, mlx3d::kBlock, [=](int64_t lo, int64_t hi) {
      for (int64_t i = lo; i < hi; ++i) mlx3d::one_splat(lin, q + 4 * i, s + 3 * i, qo + 4 * i, so + 3 * i);
    });
  });
}
