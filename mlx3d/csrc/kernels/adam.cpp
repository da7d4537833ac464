// One Adam step on float32 arrays and the finiteness check the trainer runs before it: mlx3d_adam_moment,
// mlx3d_adam_param and mlx3d_all_finite (mlx3d_kernels.h), threaded passes over the elements:
//
//   m' = b1 m + (1 - b1) g;  v' = b2 v + (1 - b2) g²;  p' = p - lr (m' / c1) / (sqrt(v' / c2) + eps)
//
// with the bias corrections c1 = 1 - b1^t, c2 = 1 - b2^t given by the caller and every scalar rounded to
// float32 first (as MLX rounds Python scalars that meet a float32 array). Each element is the same float32
// operations in this order whichever thread computes it, so results do not depend on the thread count.
// An output may be written over its first input (in place): mlx3d._core's primitives do so where MLX
// donates that input's buffer (m' over m, v' over v, p' over p).
#include <cmath>
#include <cstdint>
#include <cstring>
#include <functional>
#include <string>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

namespace mlx3d {
namespace {

constexpr int64_t kBlock = 1 << 16;  // at least this many floats per thread

// The element loops below run in chunks of kChunk: each chunk is read and computed into locals, then
// stored, so an output may be its input (in place) and the compiler still vectorizes them (AVX2 clones;
// compiled without errno for sqrt, whose argument is never negative here). Division and sqrt are correctly
// rounded in every variant, so the results do not depend on it. Full chunks have a constant length
// (kFixed): with a variable one GCC compiled the stores to `rep movs` copies, a third of the loops' time.
constexpr int kChunk = 16;

// Elements [i0, i0 + k) of a moment (k = kFixed, or k_any when kFixed is 0; k <= kChunk): out = a x + (1 - a) g,
// or (squared) a x + (1 - a) g²; out may be x.
template <int kFixed>
MLX3D_LANES_INLINE void moment_chunk(const float* g, const float* x, float* out, float a, float one_minus_a, bool squared,
                                     int64_t i0, int k_any) {
  const int k = kFixed > 0 ? kFixed : k_any;
  float c[kChunk];
  if (squared)
    for (int j = 0; j < k; ++j) c[j] = a * x[i0 + j] + one_minus_a * (g[i0 + j] * g[i0 + j]);
  else
    for (int j = 0; j < k; ++j) c[j] = a * x[i0 + j] + one_minus_a * g[i0 + j];
  for (int j = 0; j < k; ++j) out[i0 + j] = c[j];
}

// Elements [lo, hi) of a moment.
MLX3D_AVX2_CLONES void moment_range(const float* g, const float* x, float* out, float a, float one_minus_a, bool squared,
                                    int64_t lo, int64_t hi) {
  int64_t i0 = lo;
  for (; i0 + kChunk <= hi; i0 += kChunk) moment_chunk<kChunk>(g, x, out, a, one_minus_a, squared, i0, kChunk);
  if (i0 < hi) moment_chunk<0>(g, x, out, a, one_minus_a, squared, i0, static_cast<int>(hi - i0));
}

// The parameter update's scalars, rounded to float32.
struct ParamScalars {
  float lr, eps, c1, c2;
};

// Elements [i0, i0 + k) of the parameters from the new moments (k as in moment_chunk): p_out may be p.
template <int kFixed>
MLX3D_LANES_INLINE void param_chunk(const float* p, const float* m, const float* v, float* p_out, const ParamScalars& s,
                                    int64_t i0, int k_any) {
  const int k = kFixed > 0 ? kFixed : k_any;
  float pc[kChunk];
  for (int j = 0; j < k; ++j) pc[j] = p[i0 + j] - (s.lr * (m[i0 + j] / s.c1)) / (std::sqrt(v[i0 + j] / s.c2) + s.eps);
  for (int j = 0; j < k; ++j) p_out[i0 + j] = pc[j];
}

// Elements [lo, hi) of the parameters.
MLX3D_AVX2_CLONES void param_range(const float* p, const float* m, const float* v, float* p_out, ParamScalars s, int64_t lo,
                                   int64_t hi) {
  int64_t i0 = lo;
  for (; i0 + kChunk <= hi; i0 += kChunk) param_chunk<kChunk>(p, m, v, p_out, s, i0, kChunk);
  if (i0 < hi) param_chunk<0>(p, m, v, p_out, s, i0, static_cast<int>(hi - i0));
}

// Whether x is NaN or infinite: its exponent bits are all ones.
inline bool non_finite(float x) {
  uint32_t bits;
  std::memcpy(&bits, &x, 4);
  return (bits & 0x7f800000u) == 0x7f800000u;
}

// Whether n floats at a and n at b share memory.
bool overlap(const float* a, const float* b, int64_t n) {
  const std::less<const float*> before;
  return n > 0 && before(a, b + n) && before(b, a + n);
}

void check_common(int64_t n, int threads) {
  require(n >= 0, "the element count must be >= 0, got " + std::to_string(n));
  require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
}

}  // namespace
}  // namespace mlx3d

extern "C" MLX3D_API int mlx3d_adam_moment(const float* g, const float* x, int64_t n, double beta, int squared, int threads,
                                           float* out) {
  return mlx3d::guarded("mlx3d_adam_moment", [&] {
    mlx3d::check_common(n, threads);
    mlx3d::require(squared == 0 || squared == 1, "squared must be 0 (first moment) or 1 (second moment), got " + std::to_string(squared));
    mlx3d::require(n == 0 || (g && x && out), "a null pointer");
    mlx3d::require(out == x || !mlx3d::overlap(out, x, n), "out must be x (in place) or not overlap it");
    mlx3d::require(!mlx3d::overlap(out, g, n), "out must not overlap g");
    const float a = static_cast<float>(beta), one_minus_a = static_cast<float>(1.0 - beta);
    const bool sq = squared != 0;
    mlx3d::parallel_blocks(n, threads, mlx3d::kBlock,
                           [=](int64_t lo, int64_t hi) { mlx3d::moment_range(g, x, out, a, one_minus_a, sq, lo, hi); });
  });
}

extern "C" MLX3D_API int mlx3d_adam_param(const float* p, const float* m, const float* v, int64_t n, double lr, double eps, double c1,
                                          double c2, int threads, float* p_out) {
  return mlx3d::guarded("mlx3d_adam_param", [&] {
    mlx3d::check_common(n, threads);
    mlx3d::require(c1 > 0 && c2 > 0, "the bias corrections c1, c2 must be > 0, got " + std::to_string(c1) + ", " + std::to_string(c2));
    mlx3d::require(n == 0 || (p && m && v && p_out), "a null pointer");
    mlx3d::require(p_out == p || !mlx3d::overlap(p_out, p, n), "p_out must be p (in place) or not overlap it");
    mlx3d::require(!mlx3d::overlap(p_out, m, n) && !mlx3d::overlap(p_out, v, n), "p_out must not overlap m or v");
    const mlx3d::ParamScalars s{static_cast<float>(lr), static_cast<float>(eps), static_cast<float>(c1), static_cast<float>(c2)};
    mlx3d::parallel_blocks(n, threads, mlx3d::kBlock, [=](int64_t lo, int64_t hi) { mlx3d::param_range(p, m, v, p_out, s, lo, hi); });
  });
}

extern "C" MLX3D_API int mlx3d_all_finite(const float* x, int64_t n, int threads, uint8_t* finite) {
  return mlx3d::guarded("mlx3d_all_finite", [&] {
    mlx3d::check_common(n, threads);
    mlx3d::require(finite && (n == 0 || x), "a null pointer");
    std::atomic<bool> ok(true);
    std::atomic<bool>* flag = &ok;
    mlx3d::parallel_blocks(n, threads, mlx3d::kBlock, [x, flag](int64_t lo, int64_t hi) {
      uint32_t bad = 0;
      for (int64_t i = lo; i < hi; ++i) bad |= uint32_t(mlx3d::non_finite(x[i]));
      if (bad) flag->store(false, std::memory_order_relaxed);
    });
    *finite = ok.load() ? 1 : 0;
  });
}
