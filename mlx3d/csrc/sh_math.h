// Per-Gaussian math of view-dependent colour from spherical harmonics.
//
// Plain C++ with the same rules as raster_math.h (inline functions and function
// templates over the lane type F, fixed-size structs, no pointers, standard
// library calls or address-space qualifiers), so that a Metal kernel can
// include this text as its header as the rasterizer's do. The CPU primitives
// (sh_color.cpp) instantiate the basis with F = a GCC vector of floats, one
// Gaussian per lane, each lane running exactly the float operations of F =
// float. The pure-MLX reference is mlx3d.splatting.sh.eval_sh.
//
// Conventions (docs/reference/conventions.md): K = (degree+1)² coefficients per
// channel in the 3DGS order; the direction is d = mean - camera centre,
// normalised as d * (|d|² + 1e-12)^(-1/2); colour_c = 0.5 + Σ_k Y_k(u) sh[k][c],
// summed in k order; the rendered colour is max(colour, 0), whose gradient
// passes where colour > 0.
#ifndef MLX3D_SH_MATH_H
#define MLX3D_SH_MATH_H

#define SH_C0 0.28209479177387814f
#define SH_C1 0.4886025119029199f
#define SH_C2_0 1.0925484305920792f
#define SH_C2_1 -1.0925484305920792f
#define SH_C2_2 0.31539156525252005f
#define SH_C2_3 -1.0925484305920792f
#define SH_C2_4 0.5462742152960396f
#define SH_C3_0 -0.5900435899266435f
#define SH_C3_1 2.890611442640554f
#define SH_C3_2 -0.4570457994644658f
#define SH_C3_3 0.3731763325901154f
#define SH_C3_4 -0.4570457994644658f
#define SH_C3_5 1.445305721320277f
#define SH_C3_6 -0.5900435899266435f
#define SH_NORM_EPS 1e-12f
#define SH_MAX_BASES 16

#if defined(__METAL_VERSION__)
#define SH_SQRT(x) sqrt(x)
#else
#include <cmath>
#define SH_SQRT(x) std::sqrt(x)
#endif
#if defined(__GNUC__) && !defined(__METAL_VERSION__)
// Always inlined on the CPU, as raster_math.h's RM_INLINE: vector lanes passed between functions
// compiled for different instruction sets would not agree on the calling convention.
#define SH_INLINE inline __attribute__((always_inline))
#else
#define SH_INLINE inline
#endif

// Basis values Y_0..Y_15 at the unit direction (x, y, z) (entries past the degree's count are 0)
// and their partial derivatives with respect to x, y and z, taken as independent variables.
template <typename F>
struct ShBasisOf {
  F y[SH_MAX_BASES];
  F dx[SH_MAX_BASES];
  F dy[SH_MAX_BASES];
  F dz[SH_MAX_BASES];
};
typedef ShBasisOf<float> ShBasis;

inline int sh_num_bases(int degree) { return (degree + 1) * (degree + 1); }

// All lanes = v, exactly (v - (+0) is v for every v, -0 included).
template <typename F>
SH_INLINE F sh_splat(float v) {
  const F zero = {};
  return v - zero;
}

template <typename F>
SH_INLINE ShBasisOf<F> sh_basis(int degree, F x, F y, F z) {
  ShBasisOf<F> b;
  const F zero = {};
  for (int k = 0; k < SH_MAX_BASES; ++k) b.y[k] = b.dx[k] = b.dy[k] = b.dz[k] = zero;
  b.y[0] = sh_splat<F>(SH_C0);
  if (degree < 1) return b;
  b.y[1] = -SH_C1 * y;
  b.dy[1] = sh_splat<F>(-SH_C1);
  b.y[2] = SH_C1 * z;
  b.dz[2] = sh_splat<F>(SH_C1);
  b.y[3] = -SH_C1 * x;
  b.dx[3] = sh_splat<F>(-SH_C1);
  if (degree < 2) return b;
  const F xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  b.y[4] = SH_C2_0 * xy;
  b.dx[4] = SH_C2_0 * y;
  b.dy[4] = SH_C2_0 * x;
  b.y[5] = SH_C2_1 * yz;
  b.dy[5] = SH_C2_1 * z;
  b.dz[5] = SH_C2_1 * y;
  b.y[6] = SH_C2_2 * (2.0f * zz - xx - yy);
  b.dx[6] = -2.0f * SH_C2_2 * x;
  b.dy[6] = -2.0f * SH_C2_2 * y;
  b.dz[6] = 4.0f * SH_C2_2 * z;
  b.y[7] = SH_C2_3 * xz;
  b.dx[7] = SH_C2_3 * z;
  b.dz[7] = SH_C2_3 * x;
  b.y[8] = SH_C2_4 * (xx - yy);
  b.dx[8] = 2.0f * SH_C2_4 * x;
  b.dy[8] = -2.0f * SH_C2_4 * y;
  if (degree < 3) return b;
  b.y[9] = SH_C3_0 * y * (3.0f * xx - yy);
  b.dx[9] = SH_C3_0 * 6.0f * xy;
  b.dy[9] = SH_C3_0 * (3.0f * xx - 3.0f * yy);
  b.y[10] = SH_C3_1 * xy * z;
  b.dx[10] = SH_C3_1 * yz;
  b.dy[10] = SH_C3_1 * xz;
  b.dz[10] = SH_C3_1 * xy;
  b.y[11] = SH_C3_2 * y * (4.0f * zz - xx - yy);
  b.dx[11] = SH_C3_2 * -2.0f * xy;
  b.dy[11] = SH_C3_2 * (4.0f * zz - xx - 3.0f * yy);
  b.dz[11] = SH_C3_2 * 8.0f * yz;
  b.y[12] = SH_C3_3 * z * (2.0f * zz - 3.0f * xx - 3.0f * yy);
  b.dx[12] = SH_C3_3 * -6.0f * xz;
  b.dy[12] = SH_C3_3 * -6.0f * yz;
  b.dz[12] = SH_C3_3 * (6.0f * zz - 3.0f * xx - 3.0f * yy);
  b.y[13] = SH_C3_4 * x * (4.0f * zz - xx - yy);
  b.dx[13] = SH_C3_4 * (4.0f * zz - 3.0f * xx - yy);
  b.dy[13] = SH_C3_4 * -2.0f * xy;
  b.dz[13] = SH_C3_4 * 8.0f * xz;
  b.y[14] = SH_C3_5 * z * (xx - yy);
  b.dx[14] = SH_C3_5 * 2.0f * xz;
  b.dy[14] = SH_C3_5 * -2.0f * yz;
  b.dz[14] = SH_C3_5 * (xx - yy);
  b.y[15] = SH_C3_6 * x * (xx - 3.0f * yy);
  b.dx[15] = SH_C3_6 * (3.0f * xx - 3.0f * yy);
  b.dy[15] = SH_C3_6 * -6.0f * xy;
  return b;
}

// The normalised direction of d = (dx, dy, dz) and 1/|d| (epsilon-guarded).
struct ShDir {
  float x, y, z, inv_norm;
};

inline ShDir sh_direction(float dx, float dy, float dz) {
  ShDir u;
  u.inv_norm = 1.0f / SH_SQRT(dx * dx + dy * dy + dz * dz + SH_NORM_EPS);
  u.x = dx * u.inv_norm;
  u.y = dy * u.inv_norm;
  u.z = dz * u.inv_norm;
  return u;
}

// Gradient with respect to d of a function of the unit direction u = d * inv_norm, given its
// gradient (gx, gy, gz) with respect to u: (I - u uᵀ) g * inv_norm (exact, epsilon included).
struct ShVec3 {
  float x, y, z;
};

inline ShVec3 sh_direction_vjp(ShDir u, float gx, float gy, float gz) {
  const float along = u.x * gx + u.y * gy + u.z * gz;
  ShVec3 out;
  out.x = (gx - u.x * along) * u.inv_norm;
  out.y = (gy - u.y * along) * u.inv_norm;
  out.z = (gz - u.z * along) * u.inv_norm;
  return out;
}

#endif  // MLX3D_SH_MATH_H
