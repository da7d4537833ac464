// Per-Gaussian math of the EWA projection and its backward pass.
//
// Same rules as raster_math.h and sh_math.h (inline functions and function templates over the
// lane type F, fixed-size structs; no pointers, standard library calls or address-space
// qualifiers), so that a Metal kernel can include this text. Branches on a Gaussian's own values
// are selects (`?:` on masks: bool for F = float, lane masks for a GCC vector F), so that each
// lane of a vector F runs exactly the float operations of F = float. The CPU primitive is
// projection.cpp, whose lane types supply their own pm_sqrt and pm_ceil before including this
// file; the pure-MLX reference, whose every rule this reproduces, is
// mlx3d.render.projection.project_ewa (backend 'reference'), see its module docstring:
//
//   p = R m + t (camera space);  in front: near <= z <= far (finite);  zs = z there, else 1
//   L = R · R(q) · diag(s);  J = [[fx/zs, 0, -fx tx/zs²], [0, fy/zs, -fy ty/zs²]], with
//   tx, ty = x, y clamped to 1.3x the half field of view;  T = J L (2x3);  Σ2D = T Tᵀ;
//   det Σ2D = Σ of the squared 2x2 minors of T;  a, c += blur;  det += blur (a + c) + blur²
//   valid: in front, finite, det > 0, a > 0;  conic = Σ⁻¹ (0 if not valid);
//   compensation: sqrt(det Σ2D / det) (antialias) or 1, 0 if not valid;
//   radius = ceil(3 sqrt(λmax)) with λmax from max(mid² - det, 0.1), 0 if not valid or off screen;
//   means2d = (fx x/zs + cx, fy y/zs + cy), 0 behind the camera; depth = z.
#ifndef MLX3D_PROJECTION_MATH_H
#define MLX3D_PROJECTION_MATH_H

#if defined(__METAL_VERSION__)
#define PM_SQRT(x) sqrt(x)
#define PM_CEIL(x) ceil(x)
#else
#include <cmath>
#define PM_SQRT(x) std::sqrt(x)
#define PM_CEIL(x) std::ceil(x)
#endif
#if defined(__GNUC__) && !defined(__METAL_VERSION__)
// Always inlined on the CPU, as raster_math.h's RM_INLINE: vector lanes passed between functions
// compiled for different instruction sets would not agree on the calling convention.
#define PM_INLINE inline __attribute__((always_inline))
#else
#define PM_INLINE inline
#endif

#define PM_SIGMA_EXTENT 3.0f
#define PM_EIGEN_FLOOR 0.1f
#define PM_MAX_RADIUS 1073741824.0f  // 2^30
#define PM_QUAT_EPS 1e-24f

struct PmCamera {
  float rot[9];  // world-to-camera rotation, row-major
  float trans[3];
  float fx, fy, cx, cy, width, height, near_z, far_z, blur;
  int antialias;
};

// The mask type of lane type F: what comparing two F gives (bool for float).
template <typename F>
using PmMask = decltype(F() < F());

PM_INLINE float pm_sqrt(float x) { return PM_SQRT(x); }
PM_INLINE float pm_ceil(float x) { return PM_CEIL(x); }

// All lanes = v, exactly (v - (+0) is v for every v, -0 and NaN included).
template <typename F>
PM_INLINE F pm_splat(float v) {
  const F zero = {};
  return v - zero;
}

// Lane-wise isfinite: x - x is 0 exactly when x is finite (NaN otherwise).
template <typename F>
PM_INLINE PmMask<F> pm_isfinite(F x) {
#if defined(__METAL_VERSION__)
  return isfinite(x);
#else
  const F zero = {};
  return (x - x) == zero;
#endif
}

template <typename F>
struct PmGaussianOf {
  F mean[3];
  F quat[4];  // w, x, y, z, any length
  F scale[3];
};

// Everything the forward pass computes that the backward pass needs (M: F's mask type).
template <typename F>
struct PmStateOf {
  typedef PmMask<F> M;
  F p[3], zs, tx, ty;
  M in_front, clip_x, clip_y;  // clip_*: x/z or y/z was clamped
  F q[4], inv_qnorm;           // normalised quaternion, 1 / |quat|
  F r[9];                      // R(q), row-major
  F axes[9];                   // L = R_cam R(q) diag(s), row-major
  F j00, j02, j11, j12;
  F t0[3], t1[3];
  M fits;                      // Σ2D finite
  F a, b, c;                   // blurred Σ2D entries
  F det_orig, det;
  M valid;                     // positive definite (conic and compensation live)
  M live;                      // compensation's sqrt argument > 0 (antialias)
  F ratio;
  F conic[3], compensation, radius, means2d[2], depth;
  M centred;                   // means2d kept
};

template <typename F>
struct PmGradOf {
  F mean[3];
  F quat[4];
  F scale[3];
};

typedef PmGaussianOf<float> PmGaussian;
typedef PmStateOf<float> PmState;
typedef PmGradOf<float> PmGrad;

template <typename F>
PM_INLINE F pm_clip(F v, float lo, float hi) {
  return v < lo ? pm_splat<F>(lo) : (v > hi ? pm_splat<F>(hi) : v);
}

template <typename F>
PM_INLINE PmStateOf<F> pm_forward(PmCamera cam, PmGaussianOf<F> g) {
  const F zero = {}, one = pm_splat<F>(1.0f);
  PmStateOf<F> s;
  for (int i = 0; i < 3; ++i)
    s.p[i] = cam.rot[3 * i] * g.mean[0] + cam.rot[3 * i + 1] * g.mean[1] + cam.rot[3 * i + 2] * g.mean[2] + cam.trans[i];
  const F x = s.p[0], y = s.p[1], z = s.p[2];
  s.in_front = (z >= cam.near_z) & (z <= cam.far_z) & pm_isfinite(z);
  s.zs = s.in_front ? z : one;
  const float tan_x = 0.5f * cam.width / cam.fx, tan_y = 0.5f * cam.height / cam.fy;
  const F ux = x / s.zs, uy = y / s.zs;
  const float lo_x = -(cam.cx / cam.fx + 0.3f * tan_x), hi_x = (cam.width - cam.cx) / cam.fx + 0.3f * tan_x;
  const float lo_y = -(cam.cy / cam.fy + 0.3f * tan_y), hi_y = (cam.height - cam.cy) / cam.fy + 0.3f * tan_y;
  s.clip_x = (ux < lo_x) | (ux > hi_x) | (ux != ux);  // not inside [lo, hi], NaN included
  s.clip_y = (uy < lo_y) | (uy > hi_y) | (uy != uy);
  s.tx = s.zs * pm_clip(ux, lo_x, hi_x);
  s.ty = s.zs * pm_clip(uy, lo_y, hi_y);
  // R(q) of the normalised quaternion
  const F n2 = g.quat[0] * g.quat[0] + g.quat[1] * g.quat[1] + g.quat[2] * g.quat[2] + g.quat[3] * g.quat[3];
  s.inv_qnorm = 1.0f / pm_sqrt(n2 + PM_QUAT_EPS);
  for (int i = 0; i < 4; ++i) s.q[i] = g.quat[i] * s.inv_qnorm;
  const F w = s.q[0], qx = s.q[1], qy = s.q[2], qz = s.q[3];
  s.r[0] = 1.0f - 2.0f * (qy * qy + qz * qz);
  s.r[1] = 2.0f * (qx * qy - w * qz);
  s.r[2] = 2.0f * (qx * qz + w * qy);
  s.r[3] = 2.0f * (qx * qy + w * qz);
  s.r[4] = 1.0f - 2.0f * (qx * qx + qz * qz);
  s.r[5] = 2.0f * (qy * qz - w * qx);
  s.r[6] = 2.0f * (qx * qz - w * qy);
  s.r[7] = 2.0f * (qy * qz + w * qx);
  s.r[8] = 1.0f - 2.0f * (qx * qx + qy * qy);
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k)
      s.axes[3 * i + k] = cam.rot[3 * i] * (s.r[k] * g.scale[k]) + cam.rot[3 * i + 1] * (s.r[3 + k] * g.scale[k]) +
                          cam.rot[3 * i + 2] * (s.r[6 + k] * g.scale[k]);
  s.j00 = cam.fx / s.zs;
  s.j02 = -cam.fx * s.tx / (s.zs * s.zs);
  s.j11 = cam.fy / s.zs;
  s.j12 = -cam.fy * s.ty / (s.zs * s.zs);
  for (int k = 0; k < 3; ++k) {
    s.t0[k] = s.j00 * s.axes[k] + s.j02 * s.axes[6 + k];
    s.t1[k] = s.j11 * s.axes[3 + k] + s.j12 * s.axes[6 + k];
  }
  F a = s.t0[0] * s.t0[0] + s.t0[1] * s.t0[1] + s.t0[2] * s.t0[2];
  F b = s.t0[0] * s.t1[0] + s.t0[1] * s.t1[1] + s.t0[2] * s.t1[2];
  F c = s.t1[0] * s.t1[0] + s.t1[1] * s.t1[1] + s.t1[2] * s.t1[2];
  const F m01 = s.t0[0] * s.t1[1] - s.t0[1] * s.t1[0];
  const F m02 = s.t0[0] * s.t1[2] - s.t0[2] * s.t1[0];
  const F m12 = s.t0[1] * s.t1[2] - s.t0[2] * s.t1[1];
  s.det_orig = m01 * m01 + m02 * m02 + m12 * m12;
  s.fits = pm_isfinite(a) & pm_isfinite(b) & pm_isfinite(c);
  a = s.fits ? a : one;
  b = s.fits ? b : zero;
  c = s.fits ? c : one;
  s.det = s.det_orig + cam.blur * (a + c) + cam.blur * cam.blur;
  s.a = a + cam.blur;
  s.b = b;
  s.c = c + cam.blur;
  s.valid = s.in_front & s.fits & (s.det > 0.0f) & (s.a > 0.0f) & pm_isfinite(s.det);
  const F safe_det = s.valid ? s.det : one;
  const PmMask<F> none = {};
  s.live = none;
  s.ratio = zero;
  if (cam.antialias) {
    s.ratio = (s.valid ? s.det_orig : zero) / safe_det;
    s.live = s.valid & (s.ratio > 0.0f);
    s.compensation = s.live ? pm_sqrt(s.ratio) : zero;
  } else {
    s.compensation = s.valid ? one : zero;
  }
  s.conic[0] = s.valid ? s.c / safe_det : zero;
  s.conic[1] = s.valid ? -s.b / safe_det : zero;
  s.conic[2] = s.valid ? s.a / safe_det : zero;
  const F mid = 0.5f * (s.a + s.c);
  const F disc = mid * mid - safe_det;
  const F lam = mid + pm_sqrt(disc > PM_EIGEN_FLOOR ? disc : pm_splat<F>(PM_EIGEN_FLOOR));
  const F radius = pm_ceil(PM_SIGMA_EXTENT * pm_sqrt(lam > 0.0f ? lam : zero));
  s.means2d[0] = cam.fx * x / s.zs + cam.cx;
  s.means2d[1] = cam.fy * y / s.zs + cam.cy;
  const PmMask<F> on_screen = (s.means2d[0] + radius > 0.0f) & (s.means2d[0] - radius < cam.width) &
                              (s.means2d[1] + radius > 0.0f) & (s.means2d[1] - radius < cam.height);
  s.radius = (s.valid & on_screen & pm_isfinite(radius)) ? (radius < PM_MAX_RADIUS ? radius : pm_splat<F>(PM_MAX_RADIUS)) : zero;
  s.centred = s.in_front & pm_isfinite(s.means2d[0]) & pm_isfinite(s.means2d[1]);
  s.means2d[0] = s.centred ? s.means2d[0] : zero;
  s.means2d[1] = s.centred ? s.means2d[1] : zero;
  s.depth = z;
  return s;
}

// Gradients with respect to the Gaussian's mean, quaternion and scales of a loss whose gradients
// with respect to means2d (g2), conic (gc), depth (gd) and compensation (gk) are given.
template <typename F>
PM_INLINE PmGradOf<F> pm_backward(PmCamera cam, PmGaussianOf<F> g, PmStateOf<F> s, F g2x, F g2y, F gc0, F gc1, F gc2, F gd, F gk) {
  const F zero = {};
  F dp[3] = {zero, zero, gd};  // camera-space position
  F dzs = zero;
  dp[0] = s.centred ? dp[0] + g2x * cam.fx / s.zs : dp[0];
  dp[1] = s.centred ? dp[1] + g2y * cam.fy / s.zs : dp[1];
  dzs = s.centred ? dzs + -(g2x * cam.fx * s.p[0] + g2y * cam.fy * s.p[1]) / (s.zs * s.zs) : dzs;
  // blurred Σ2D entries (a, b, c) and the unblurred determinant; dK = -K dΣ K (the conic's own
  // expression, as the reference's custom VJP)
  const F A = s.conic[0], B = s.conic[1], C = s.conic[2];
  F da = s.valid ? -((gc0 * A) * A + (gc1 * A) * B + (gc2 * B) * B) : zero;
  const F db = s.valid ? -(2.0f * (gc0 * A) * B + gc1 * (A * C + B * B) + 2.0f * (gc2 * B) * C) : zero;
  F dc = s.valid ? -((gc0 * B) * B + (gc1 * B) * C + (gc2 * C) * C) : zero;
  F ddet_orig = zero;
  if (cam.antialias) {
    const F dratio = gk * 0.5f / s.compensation;  // d sqrt(r) = dr / (2 sqrt(r))
    const F ddet = -dratio * s.ratio / s.det;
    ddet_orig = s.live ? ddet_orig + dratio / s.det + ddet : ddet_orig;  // det = det_orig + blur (a + c) + blur²
    da = s.live ? da + cam.blur * ddet : da;
    dc = s.live ? dc + cam.blur * ddet : dc;
  }
  F dt0[3], dt1[3];
  for (int k = 0; k < 3; ++k) {
    dt0[k] = s.fits ? 2.0f * da * s.t0[k] + db * s.t1[k] : zero;
    dt1[k] = s.fits ? db * s.t0[k] + 2.0f * dc * s.t1[k] : zero;
  }
  {
    const PmMask<F> nonzero = ddet_orig != 0.0f;
    const F m01 = s.t0[0] * s.t1[1] - s.t0[1] * s.t1[0];
    const F m02 = s.t0[0] * s.t1[2] - s.t0[2] * s.t1[0];
    const F m12 = s.t0[1] * s.t1[2] - s.t0[2] * s.t1[1];
    const F g01 = 2.0f * m01 * ddet_orig, g02 = 2.0f * m02 * ddet_orig, g12 = 2.0f * m12 * ddet_orig;
    dt0[0] = nonzero ? dt0[0] + (g01 * s.t1[1] + g02 * s.t1[2]) : dt0[0];
    dt0[1] = nonzero ? dt0[1] + (-g01 * s.t1[0] + g12 * s.t1[2]) : dt0[1];
    dt0[2] = nonzero ? dt0[2] + (-g02 * s.t1[0] - g12 * s.t1[1]) : dt0[2];
    dt1[0] = nonzero ? dt1[0] + (-g01 * s.t0[1] - g02 * s.t0[2]) : dt1[0];
    dt1[1] = nonzero ? dt1[1] + (g01 * s.t0[0] - g12 * s.t0[2]) : dt1[1];
    dt1[2] = nonzero ? dt1[2] + (g02 * s.t0[0] + g12 * s.t0[1]) : dt1[2];
  }
  // T = J L
  F dj00 = zero, dj02 = zero, dj11 = zero, dj12 = zero, dax[9];
  for (int k = 0; k < 3; ++k) {
    dj00 = dj00 + dt0[k] * s.axes[k];
    dj02 = dj02 + dt0[k] * s.axes[6 + k];
    dj11 = dj11 + dt1[k] * s.axes[3 + k];
    dj12 = dj12 + dt1[k] * s.axes[6 + k];
    dax[k] = dt0[k] * s.j00;
    dax[3 + k] = dt1[k] * s.j11;
    dax[6 + k] = dt0[k] * s.j02 + dt1[k] * s.j12;
  }
  const F zs2 = s.zs * s.zs, zs3 = zs2 * s.zs;
  dzs = dzs + (-cam.fx / zs2 * dj00 + 2.0f * cam.fx * s.tx / zs3 * dj02 - cam.fy / zs2 * dj11 + 2.0f * cam.fy * s.ty / zs3 * dj12);
  const F dtx = -cam.fx / zs2 * dj02, dty = -cam.fy / zs2 * dj12;
  // tx = zs clip(x / zs): x itself inside the clamp, zs · bound outside it
  dzs = s.clip_x ? dzs + dtx * (s.tx / s.zs) : dzs;
  dp[0] = s.clip_x ? dp[0] : dp[0] + dtx;
  dzs = s.clip_y ? dzs + dty * (s.ty / s.zs) : dzs;
  dp[1] = s.clip_y ? dp[1] : dp[1] + dty;
  dp[2] = s.in_front ? dp[2] + dzs : dp[2];
  PmGradOf<F> out;
  for (int j = 0; j < 3; ++j) out.mean[j] = cam.rot[j] * dp[0] + cam.rot[3 + j] * dp[1] + cam.rot[6 + j] * dp[2];
  // L = R_cam · R(q) · diag(s): dRS = R_camᵀ dL
  F gr[9];
  for (int k = 0; k < 3; ++k) {
    F ds = zero;
    for (int j = 0; j < 3; ++j) {
      const F drs = cam.rot[j] * dax[k] + cam.rot[3 + j] * dax[3 + k] + cam.rot[6 + j] * dax[6 + k];
      gr[3 * j + k] = drs * g.scale[k];
      ds = ds + drs * s.r[3 * j + k];
    }
    out.scale[k] = ds;
  }
  const F w = s.q[0], x = s.q[1], y = s.q[2], z = s.q[3];
  F dq[4];
  dq[0] = 2.0f * (-z * gr[1] + y * gr[2] + z * gr[3] - x * gr[5] - y * gr[6] + x * gr[7]);
  dq[1] = 2.0f * (y * gr[1] + z * gr[2] + y * gr[3] - 2.0f * x * gr[4] - w * gr[5] + z * gr[6] + w * gr[7] - 2.0f * x * gr[8]);
  dq[2] = 2.0f * (-2.0f * y * gr[0] + x * gr[1] + w * gr[2] + x * gr[3] + z * gr[5] - w * gr[6] + z * gr[7] - 2.0f * y * gr[8]);
  dq[3] = 2.0f * (-2.0f * z * gr[0] - w * gr[1] + x * gr[2] + w * gr[3] - 2.0f * z * gr[4] + y * gr[5] + x * gr[6] + y * gr[7]);
  // normalisation q = quat / |quat|: (I - q qᵀ) dq / |quat|
  const F along = w * dq[0] + x * dq[1] + y * dq[2] + z * dq[3];
  for (int i = 0; i < 4; ++i) out.quat[i] = (dq[i] - s.q[i] * along) * s.inv_qnorm;
  return out;
}

#endif  // MLX3D_PROJECTION_MATH_H
