// Per-pixel math of the 3DGS rasterizer, shared by both compiled backends.
//
// This exact text is compiled as C++ (included by rasterize.cpp, the CPU MLX
// primitives) and as Metal Shading Language (mlx3d/render/raster_metal.py reads
// this file at import time and passes it as the `header` of its
// mx.fast.metal_kernel kernels), so the CPU tests exercise the math the Metal
// kernels run.
//
// Rules for this file: `inline` function templates over the lane type F, using
// only arithmetic, comparisons, `&` on comparison results and `?:`. Metal
// instantiates them with F = float (one pixel per thread); the CPU with F = a
// GCC vector of floats (several pixels at once; comparisons then give lane
// masks and `?:` selects per lane) or with float. No pointers, references,
// standard library calls or address-space qualifiers; C++-only or Metal-only
// lines go behind `__METAL_VERSION__`.
//
// Conventions (docs/guides/rendering.md): pixel (row i, col j) has its centre
// at (j + 0.5, i + 0.5); d = mean2d - pixel; conic (a, b, c) are the entries of
// the inverse 2D covariance [[a, b], [b, c]]. Per pixel, front to back:
//   power = -0.5 * (a dx² + c dy²) - b dx dy;      skip if power > 0
//   alpha = min(0.99, opacity * exp(power));       skip if alpha < 1/255
//   next_T = T * (1 - alpha);                      stop if next_T < 1e-4 (RM_T_MIN)
//   accum += feature * (alpha * T);  T = next_T
// A Gaussian whose power or alpha is NaN is skipped too (the comparisons below
// are written so that NaN fails the "keep" test).
#ifndef MLX3D_RASTER_MATH_H
#define MLX3D_RASTER_MATH_H

#if defined(__GNUC__) && !defined(__METAL_VERSION__)
// Always inlined on the CPU: a call that passes vector lanes across functions
// compiled for different instruction sets (the AVX2 variant) would not agree on
// the calling convention.
#define RM_INLINE inline __attribute__((always_inline))
#else
#define RM_INLINE inline
#endif
#define RM_ALPHA_MAX 0.99f
#define RM_ALPHA_MIN (1.0f / 255.0f)
#define RM_T_MIN 0.0001f
#define RM_EXP_LO (-87.33654f)
#define RM_EXP_HI 88.0f

// 2^n for an integral-valued n in [-126, 127] (exponent bits). Vector lane
// types provide their own overload before including this file.
#if defined(__METAL_VERSION__)
RM_INLINE float rm_pow2i(float n) {
  return as_type<float>(((int)n + 127) << 23);
}
#else
#include <cstring>
RM_INLINE float rm_pow2i(float n) {
  int bits = ((int)n + 127) << 23;
  float f;
  std::memcpy(&f, &bits, sizeof(f));
  return f;
}
#endif

// exp(x), branch-free, within ~2 ulp of the exact value for x in
// [RM_EXP_LO, RM_EXP_HI]; 0 below that range, NaN for NaN. Inputs above
// RM_EXP_HI are clamped (the rasterizer only calls it on power <= 0).
// Cody-Waite range reduction x = n ln2 + r and a degree-6 polynomial (Cephes expf).
template <typename F>
RM_INLINE F rm_exp(F x) {
  F xc = x > RM_EXP_LO ? x : RM_EXP_LO;  // also maps NaN to RM_EXP_LO
  xc = xc < RM_EXP_HI ? xc : RM_EXP_HI;
  // n = round(xc / ln2): adding and subtracting 1.5 * 2^23 rounds to nearest.
  F n = (xc * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
  F r = xc - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  F p = r * 1.9875691500e-4f + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * (r * r) + r + 1.0f;
  F y = p * rm_pow2i(n);
  return x >= RM_EXP_LO ? y : (x < RM_EXP_LO ? 0.0f : x);
}

// The Gaussian's exponent at offset (dx, dy) = mean2d - pixel centre.
template <typename F>
RM_INLINE F rm_power(F a, F b, F c, F dx, F dy) {
  return -0.5f * (a * dx * dx + c * dy * dy) - b * dx * dy;
}

// Alpha of a Gaussian at a pixel, given g = rm_exp(power). Returns 0 when the
// Gaussian is skipped (power > 0, alpha < 1/255, or NaN); a kept Gaussian
// always has alpha in [1/255, 0.99], so `alpha > 0` means "kept".
template <typename F>
RM_INLINE F rm_alpha(F opacity, F g, F power) {
  F raw = opacity * g;
  F alpha = raw > RM_ALPHA_MAX ? RM_ALPHA_MAX : raw;  // NaN stays NaN
  return ((power <= 0.0f) & (alpha >= RM_ALPHA_MIN)) ? alpha : 0.0f;
}

// Transmittance after a kept Gaussian; the pixel stops (and the Gaussian does
// not contribute) when it is below RM_T_MIN.
template <typename F>
RM_INLINE F rm_next_T(F T, F alpha) {
  return T * (1.0f - alpha);
}

// ---------------------------------------------------------------- backward
// The backward pass walks a pixel's kept Gaussians back to front, starting
// from T = T_final, and recovers the transmittance in front of each one.
template <typename F>
RM_INLINE F rm_T_before(F T_after, F alpha) {
  return T_after / (1.0f - alpha);
}

// "behind" is the colour composited behind the current Gaussian divided by the
// transmittance just behind it: B_i = Σ_{j>i} f_j α_j T_j / T_{i+1}. Stepping
// from Gaussian i+1 (prev_alpha, prev_feature) to i: B_i = α f + (1 - α) B_{i+1}.
// The Metal kernel runs it per channel; the CPU kernel runs it once on the
// colours dotted with dL/daccum (f · dL/daccum), since dL/dα needs B only
// through B · dL/daccum.
template <typename F>
RM_INLINE F rm_behind(F behind, F prev_alpha, F prev_feature) {
  return prev_alpha * prev_feature + (1.0f - prev_alpha) * behind;
}

// dL/dα_i for a kept Gaussian with transmittance T_before in front of it:
// accum = Σ f_j α_j T_j gives T_before · Σ_ch (f - B_i) · dL/daccum (passed
// here as `dot`), and alpha_out = 1 - T_final gives dL/dalpha_out · T_final / (1 - α_i).
template <typename F>
RM_INLINE F rm_dl_dalpha(F T_before, F dot, F T_final, F dl_dalpha_out, F alpha) {
  return T_before * dot + dl_dalpha_out * T_final / (1.0f - alpha);
}

// Gradients of one (pixel, Gaussian) pair w.r.t. the Gaussian's parameters.
template <typename F>
struct RmGaussGrad {
  F mean_x;
  F mean_y;
  F conic_a;
  F conic_b;
  F conic_c;
  F opacity;
};

// From dL/dα through α = min(0.99, opacity · exp(power)): zero where the
// clamp is active (opacity · exp(power) > 0.99), else
//   dL/dopacity = g · dL/dα,  dL/dpower = opacity · g · dL/dα,
//   dpower/dmean = -(a dx + b dy, b dx + c dy),
//   dpower/d(a, b, c) = (-dx²/2, -dx dy, -dy²/2).
template <typename F>
RM_INLINE RmGaussGrad<F> rm_gaussian_grad(F a, F b, F c, F dx, F dy, F opacity, F g, F dl_dalpha) {
  F raw = opacity * g;
  F dl_dpower = raw > RM_ALPHA_MAX ? 0.0f : raw * dl_dalpha;
  RmGaussGrad<F> out;
  out.opacity = raw > RM_ALPHA_MAX ? 0.0f : g * dl_dalpha;
  out.mean_x = -dl_dpower * (a * dx + b * dy);
  out.mean_y = -dl_dpower * (b * dx + c * dy);
  out.conic_a = -0.5f * dl_dpower * (dx * dx);
  out.conic_b = -dl_dpower * (dx * dy);
  out.conic_c = -0.5f * dl_dpower * (dy * dy);
  return out;
}

#endif  // MLX3D_RASTER_MATH_H
