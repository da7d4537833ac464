// View-dependent colour from spherical harmonics, threaded over Gaussians: mlx3d_sh_forward and
// mlx3d_sh_backward (mlx3d_kernels.h; the math, shared with Metal: sh_math.h).
//
// Gaussians are taken kLanes at a time (lane-wise gathers of their directions and coefficients), and every
// Gaussian is computed by one thread from its own inputs only, so results are bitwise identical for any
// thread count, and for one array or two blocks.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"
#include "../sh_math.h"

namespace mlx3d {
namespace {

constexpr int kBlock = 4096;  // at least this many Gaussians per thread

struct ShInputs {
  const float* block[2];  // (N, K0, 3) and (N, K1, 3); block[1] unused when K1 = 0
  int kb[2];              // K0, K1
  const float* means;     // (N, 3)
  const float* centre;    // (3,)
  int64_t n;
  int k;                  // K0 + K1
  int degree;
};

// Up to kLanes consecutive Gaussians [i0, i0 + count), lanes past `count` repeating the last one, with
// their directions and first `bases` coefficients gathered lane-wise (coef[3k + c][lane]).
struct Batch {
  int count;
  alignas(32) float x[kLanes], y[kLanes], z[kLanes], inv_norm[kLanes];  // the directions (ShDir), lane-wise
  alignas(32) float coef[3 * SH_MAX_BASES][kLanes];
};

MLX3D_LANES_INLINE void gather(const ShInputs& in, int64_t i0, int64_t hi, int bases, Batch& b) {
  b.count = static_cast<int>(std::min<int64_t>(kLanes, hi - i0));
  for (int j = 0; j < kLanes; ++j) {
    const int64_t i = i0 + std::min(j, b.count - 1);
    const float* m = in.means + 3 * i;
    const ShDir u = sh_direction(m[0] - in.centre[0], m[1] - in.centre[1], m[2] - in.centre[2]);
    b.x[j] = u.x;
    b.y[j] = u.y;
    b.z[j] = u.z;
    b.inv_norm[j] = u.inv_norm;
    int q0 = 0;  // first float of the block in coef
    for (int blk = 0; blk < 2 && q0 < 3 * bases; ++blk) {
      const float* c = in.block[blk] + i * 3 * in.kb[blk];
      const int floats = std::min(3 * in.kb[blk], 3 * bases - q0);
      for (int q = 0; q < floats; ++q) b.coef[q0 + q][j] = c[q];
      q0 += 3 * in.kb[blk];
    }
  }
}

// Unclamped colours of a batch seen along the basis y (lane-wise), summed in k order.
MLX3D_LANES_INLINE void colour_of(const Batch& batch, int bases, const Lanes* y, Lanes* colour) {
  for (int ch = 0; ch < 3; ++ch) {
    Lanes acc = y[0] * lanes_at(batch.coef[ch]);
    for (int k = 1; k < bases; ++k) acc = acc + y[k] * lanes_at(batch.coef[3 * k + ch]);
    colour[ch] = acc + 0.5f;
  }
}

MLX3D_AVX2_CLONES void forward_range(const ShInputs& in, int64_t lo, int64_t hi, float* rgb) {
  const int bases = sh_num_bases(in.degree);
  Batch batch;
  for (int64_t i0 = lo; i0 < hi; i0 += kLanes) {
    gather(in, i0, hi, bases, batch);
    const ShBasisOf<Lanes> b = sh_basis(in.degree, lanes_at(batch.x), lanes_at(batch.y), lanes_at(batch.z));
    Lanes colour[3];
    colour_of(batch, bases, b.y, colour);
    alignas(32) float c[3][kLanes];
    for (int ch = 0; ch < 3; ++ch) put_lanes(c[ch], colour[ch]);
    for (int j = 0; j < batch.count; ++j)
      for (int ch = 0; ch < 3; ++ch) rgb[3 * (i0 + j) + ch] = c[ch][j] > 0.0f ? c[ch][j] : 0.0f;
  }
}

// d_block: dL/d(each block), laid out as the inputs.
MLX3D_AVX2_CLONES void backward_range(const ShInputs& in, const float* cot, float* const d_block[2], float* d_means, int64_t lo,
                                      int64_t hi) {
  const int bases = sh_num_bases(in.degree);
  Batch batch;
  alignas(32) float ds[3 * SH_MAX_BASES][kLanes];  // dL/dsh[k][c] of each lane, for k < bases
  for (int64_t i0 = lo; i0 < hi; i0 += kLanes) {
    gather(in, i0, hi, bases, batch);
    const ShBasisOf<Lanes> b = sh_basis(in.degree, lanes_at(batch.x), lanes_at(batch.y), lanes_at(batch.z));
    Lanes colour[3];
    colour_of(batch, bases, b.y, colour);
    // dL/dcolour: the cotangent where the colour is above the clamp, else 0.
    alignas(32) float c[3][kLanes], g[3][kLanes];
    for (int ch = 0; ch < 3; ++ch) put_lanes(c[ch], colour[ch]);
    for (int j = 0; j < kLanes; ++j)
      for (int ch = 0; ch < 3; ++ch) g[ch][j] = c[ch][j] > 0.0f ? cot[3 * (i0 + std::min(j, batch.count - 1)) + ch] : 0.0f;
    const Lanes gl[3] = {lanes_at(g[0]), lanes_at(g[1]), lanes_at(g[2])};
    Lanes gx = {}, gy = {}, gz = {};
    for (int k = 0; k < bases; ++k) {
      Lanes along = {};  // Σ_c g_c sh[k][c]
      for (int ch = 0; ch < 3; ++ch) {
        put_lanes(ds[3 * k + ch], gl[ch] * b.y[k]);
        along = along + gl[ch] * lanes_at(batch.coef[3 * k + ch]);
      }
      if (k > 0) {
        gx = gx + along * b.dx[k];
        gy = gy + along * b.dy[k];
        gz = gz + along * b.dz[k];
      }
    }
    alignas(32) float gxs[kLanes], gys[kLanes], gzs[kLanes];
    put_lanes(gxs, gx);
    put_lanes(gys, gy);
    put_lanes(gzs, gz);
    for (int j = 0; j < batch.count; ++j) {
      const int64_t i = i0 + j;
      int q0 = 0;  // first float of the block in ds
      for (int blk = 0; blk < 2; ++blk) {
        float* d = d_block[blk] + i * 3 * in.kb[blk];
        const int floats = 3 * in.kb[blk], live = std::max(0, std::min(floats, 3 * bases - q0));
        for (int q = 0; q < live; ++q) d[q] = ds[q0 + q][j];
        for (int q = live; q < floats; ++q) d[q] = 0.0f;
        q0 += floats;
      }
      const ShDir u{batch.x[j], batch.y[j], batch.z[j], batch.inv_norm[j]};
      const ShVec3 dm = sh_direction_vjp(u, gxs[j], gys[j], gzs[j]);
      d_means[3 * i] = dm.x;
      d_means[3 * i + 1] = dm.y;
      d_means[3 * i + 2] = dm.z;
    }
  }
}

void run_forward(ShInputs in, int num_threads, float* rgb) {
  parallel_blocks(in.n, num_threads, kBlock, [in, rgb](int64_t lo, int64_t hi) { forward_range(in, lo, hi, rgb); });
}

void run_backward(ShInputs in, const float* cot, int num_threads, float* const d_block[2], float* d_means) {
  parallel_blocks(in.n, num_threads, kBlock,
                  [in, cot, d_block, d_means](int64_t lo, int64_t hi) { backward_range(in, cot, d_block, d_means, lo, hi); });
}

ShInputs sh_inputs(const float* block0, int64_t k0, const float* block1, int64_t k1, const float* means, const float* centre,
                   int64_t n, int degree, int threads) {
  require(degree >= 0 && degree <= 3, "degree must be 0..3, got " + std::to_string(degree));
  require(n >= 0 && n <= INT32_MAX, "the count of Gaussians must be 0..2^31-1, got " + std::to_string(n));
  require(k0 >= 1 && k1 >= 0 && k0 + k1 <= (1 << 20), "the blocks must hold 1 to 2^20 coefficients, got " + std::to_string(k0) + " + " + std::to_string(k1));
  require(k0 + k1 >= sh_num_bases(degree), "degree " + std::to_string(degree) + " needs at least " + std::to_string(sh_num_bases(degree)) +
                                               " coefficients, got " + std::to_string(k0 + k1));
  require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
  require(n == 0 || (block0 && means && centre && (k1 == 0 || block1)), "a null input pointer");
  ShInputs in{};
  in.block[0] = block0;
  in.block[1] = k1 ? block1 : nullptr;
  in.kb[0] = static_cast<int>(k0);
  in.kb[1] = static_cast<int>(k1);
  in.means = means;
  in.centre = centre;
  in.n = n;
  in.k = static_cast<int>(k0 + k1);
  in.degree = degree;
  return in;
}

}  // namespace
}  // namespace mlx3d

extern "C" {

MLX3D_API int mlx3d_sh_forward(const float* block0, int64_t k0, const float* block1, int64_t k1, const float* means,
                               const float* centre, int64_t n, int degree, int threads, float* rgb) {
  return mlx3d::guarded("mlx3d_sh_forward", [&] {
    const mlx3d::ShInputs in = mlx3d::sh_inputs(block0, k0, block1, k1, means, centre, n, degree, threads);
    mlx3d::require(n == 0 || rgb, "a null output pointer");
    mlx3d::run_forward(in, threads, rgb);
  });
}

MLX3D_API int mlx3d_sh_backward(const float* block0, int64_t k0, const float* block1, int64_t k1, const float* means,
                                const float* centre, int64_t n, int degree, const float* cot, int threads,
                                float* d_block0, float* d_block1, float* d_means) {
  return mlx3d::guarded("mlx3d_sh_backward", [&] {
    const mlx3d::ShInputs in = mlx3d::sh_inputs(block0, k0, block1, k1, means, centre, n, degree, threads);
    mlx3d::require(n == 0 || (cot && d_block0 && d_means && (k1 == 0 || d_block1)), "a null pointer among the gradient's");
    float* const d_block[2] = {d_block0, k1 ? d_block1 : nullptr};
    mlx3d::run_backward(in, cot, threads, d_block, d_means);
  });
}

}  // extern "C"
