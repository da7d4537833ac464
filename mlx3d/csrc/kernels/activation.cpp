// The parameter activations of a training step, exp (log-scales -> scales) and sigmoid (opacity logits ->
// opacities), threaded over the elements: mlx3d_exp and mlx3d_sigmoid (mlx3d_kernels.h). Each element is
// computed by MLX's own scalar algorithm (mlx/backend/cpu/simd/math.h and unary_ops.h, written out below),
// so the results are bit for bit those of MLX's CPU mx.exp / mx.sigmoid, which run on one core (and, on
// x86-64 Linux, one element at a time). The element loops inline it (flatten) into an FMA variant
// (MLX3D_FMA_CLONES), where its std::fma calls are one instruction each instead of calls into libm: 3-4x
// faster, the same bits (fma is exactly rounded either way).
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

#if defined(__GNUC__)
#define MLX3D_FLATTEN __attribute__((flatten))
#else
#define MLX3D_FLATTEN
#endif

namespace mlx3d {
namespace {

constexpr int64_t kBlock = 1 << 15;  // at least this many elements per thread

// MLX's scalar exp and sigmoid: the algorithm of mlx::core::simd::exp at one element (Simd<float, 1>) and of
// mlx::core::detail::Sigmoid, from MLX 0.32 (https://github.com/ml-explore/mlx, MIT License, Copyright © 2023
// Apple Inc.; the polynomial's constants from Cephes by way of akohlmey/fastermath), with its operations in
// its order.
//
// e^x = 2^(x log2 e) = 2^i p(f): i = floor(x log2 e + 0.5), the sum and the floor in double (MLX adds the
// double 0.5 to the float product), f the float rest in [-0.5, 0.5], p a degree-6 polynomial in Horner form
// with std::fma, 2^i made from its exponent bits. NaN gives the input itself, x > 88 inf and x < -88 0.
inline float mlx_exp(float x_init) {
  float x = x_init * 1.442695f;  // log2(e)
  const float ipart = static_cast<float>(std::floor(static_cast<double>(x) + 0.5));
  const float fpart = x - ipart;
  x = 1.535336188319500e-4f;
  x = std::fma(x, fpart, 1.339887440266574e-3f);
  x = std::fma(x, fpart, 9.618437357674640e-3f);
  x = std::fma(x, fpart, 5.550332471162809e-2f);
  x = std::fma(x, fpart, 2.402264791363012e-1f);
  x = std::fma(x, fpart, 6.931472028550421e-1f);
  x = std::fma(x, fpart, 1.000000000000000f);
  // 2^ipart: (ipart + 127) << 23 as float bits. ipart is in [-127, 127] wherever the product is kept
  // (|x_init| <= 88); it is clamped to that range so that the int conversion is defined for the others too
  // (NaN, inf, huge), whose product the selects below replace.
  const float e = ipart > -127.0f ? (ipart < 127.0f ? ipart : 127.0f) : -127.0f;
  const uint32_t bits = static_cast<uint32_t>(static_cast<int32_t>(e) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, 4);
  float result = std::isnan(x_init) ? x_init : scale * x;
  result = x_init > 88.0f ? std::numeric_limits<float>::infinity() : result;
  result = x_init < -88.0f ? 0.0f : result;
  return result;
}

// sigmoid(x) = 1 / (1 + e^-x), from y = 1 / (1 + e^|x|): y for x < 0, else 1 - y.
inline float mlx_sigmoid(float x) {
  const float y = 1.0f / (1.0f + mlx_exp(std::abs(x)));
  return x < 0.0f ? y : 1.0f - y;
}

MLX3D_FMA_CLONES MLX3D_FLATTEN void exp_range(const float* x, float* y, int64_t lo, int64_t hi) {
  for (int64_t i = lo; i < hi; ++i) y[i] = mlx_exp(x[i]);
}

MLX3D_FMA_CLONES MLX3D_FLATTEN void sigmoid_range(const float* x, float* y, int64_t lo, int64_t hi) {
  for (int64_t i = lo; i < hi; ++i) y[i] = mlx_sigmoid(x[i]);
}

template <class Range>
int run(const char* name, const float* x, int64_t n, int threads, float* y, Range range) {
  return guarded(name, [&] {
    require(n >= 0, "the element count must be >= 0, got " + std::to_string(n));
    require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
    require(n == 0 || (x && y), "a null pointer");
    parallel_blocks(n, threads, kBlock, [x, y, range](int64_t lo, int64_t hi) { range(x, y, lo, hi); });
  });
}

}  // namespace
}  // namespace mlx3d

extern "C" MLX3D_API int mlx3d_exp(const float* x, int64_t n, int threads, float* y) {
  return mlx3d::run("mlx3d_exp", x, n, threads, y, mlx3d::exp_range);
}

extern "C" MLX3D_API int mlx3d_sigmoid(const float* x, int64_t n, int threads, float* y) {
  return mlx3d::run("mlx3d_sigmoid", x, n, threads, y, mlx3d::sigmoid_range);
}
