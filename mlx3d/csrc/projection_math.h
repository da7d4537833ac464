// Per-Gaussian math of the EWA projection and its backward pass.
//
// Same rules as raster_math.h and sh_math.h (inline functions on float and fixed-size
// structs; no pointers, standard library calls or address-space qualifiers), so that a Metal
// kernel can include this text. The CPU primitive is projection.cpp; the pure-MLX reference,
// whose every rule this reproduces, is mlx3d.render.projection.project_ewa (backend
// 'reference'), see its module docstring:
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
#define PM_ISFINITE(x) isfinite(x)
#else
#include <cmath>
#define PM_SQRT(x) std::sqrt(x)
#define PM_CEIL(x) std::ceil(x)
#define PM_ISFINITE(x) std::isfinite(x)
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

struct PmGaussian {
  float mean[3];
  float quat[4];  // w, x, y, z, any length
  float scale[3];
};

// Everything the forward pass computes that the backward pass needs.
struct PmState {
  float p[3], zs, tx, ty;
  bool in_front, clip_x, clip_y;  // clip_*: x/z or y/z was clamped
  float q[4], inv_qnorm;          // normalised quaternion, 1 / |quat|
  float r[9];                     // R(q), row-major
  float axes[9];                  // L = R_cam R(q) diag(s), row-major
  float j00, j02, j11, j12;
  float t0[3], t1[3];
  bool fits;                      // Σ2D finite
  float a, b, c;                  // blurred Σ2D entries
  float det_orig, det;
  bool valid;                     // positive definite (conic and compensation live)
  bool live;                      // compensation's sqrt argument > 0 (antialias)
  float ratio;
  float conic[3], compensation, radius, means2d[2], depth;
  bool centred;                   // means2d kept
};

inline float pm_clip(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }

inline PmState pm_forward(PmCamera cam, PmGaussian g) {
  PmState s;
  for (int i = 0; i < 3; ++i)
    s.p[i] = cam.rot[3 * i] * g.mean[0] + cam.rot[3 * i + 1] * g.mean[1] + cam.rot[3 * i + 2] * g.mean[2] + cam.trans[i];
  const float x = s.p[0], y = s.p[1], z = s.p[2];
  s.in_front = z >= cam.near_z && z <= cam.far_z && PM_ISFINITE(z);
  s.zs = s.in_front ? z : 1.0f;
  const float tan_x = 0.5f * cam.width / cam.fx, tan_y = 0.5f * cam.height / cam.fy;
  const float ux = x / s.zs, uy = y / s.zs;
  const float lo_x = -(cam.cx / cam.fx + 0.3f * tan_x), hi_x = (cam.width - cam.cx) / cam.fx + 0.3f * tan_x;
  const float lo_y = -(cam.cy / cam.fy + 0.3f * tan_y), hi_y = (cam.height - cam.cy) / cam.fy + 0.3f * tan_y;
  s.clip_x = !(ux >= lo_x && ux <= hi_x);
  s.clip_y = !(uy >= lo_y && uy <= hi_y);
  s.tx = s.zs * pm_clip(ux, lo_x, hi_x);
  s.ty = s.zs * pm_clip(uy, lo_y, hi_y);
  // R(q) of the normalised quaternion
  const float n2 = g.quat[0] * g.quat[0] + g.quat[1] * g.quat[1] + g.quat[2] * g.quat[2] + g.quat[3] * g.quat[3];
  s.inv_qnorm = 1.0f / PM_SQRT(n2 + PM_QUAT_EPS);
  for (int i = 0; i < 4; ++i) s.q[i] = g.quat[i] * s.inv_qnorm;
  const float w = s.q[0], qx = s.q[1], qy = s.q[2], qz = s.q[3];
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
  float a = s.t0[0] * s.t0[0] + s.t0[1] * s.t0[1] + s.t0[2] * s.t0[2];
  float b = s.t0[0] * s.t1[0] + s.t0[1] * s.t1[1] + s.t0[2] * s.t1[2];
  float c = s.t1[0] * s.t1[0] + s.t1[1] * s.t1[1] + s.t1[2] * s.t1[2];
  const float m01 = s.t0[0] * s.t1[1] - s.t0[1] * s.t1[0];
  const float m02 = s.t0[0] * s.t1[2] - s.t0[2] * s.t1[0];
  const float m12 = s.t0[1] * s.t1[2] - s.t0[2] * s.t1[1];
  s.det_orig = m01 * m01 + m02 * m02 + m12 * m12;
  s.fits = PM_ISFINITE(a) && PM_ISFINITE(b) && PM_ISFINITE(c);
  if (!s.fits) a = 1.0f, b = 0.0f, c = 1.0f;
  s.det = s.det_orig + cam.blur * (a + c) + cam.blur * cam.blur;
  s.a = a + cam.blur;
  s.b = b;
  s.c = c + cam.blur;
  s.valid = s.in_front && s.fits && s.det > 0.0f && s.a > 0.0f && PM_ISFINITE(s.det);
  const float safe_det = s.valid ? s.det : 1.0f;
  s.live = false;
  s.ratio = 0.0f;
  if (cam.antialias) {
    s.ratio = (s.valid ? s.det_orig : 0.0f) / safe_det;
    s.live = s.valid && s.ratio > 0.0f;
    s.compensation = s.live ? PM_SQRT(s.ratio) : 0.0f;
  } else {
    s.compensation = s.valid ? 1.0f : 0.0f;
  }
  s.conic[0] = s.valid ? s.c / safe_det : 0.0f;
  s.conic[1] = s.valid ? -s.b / safe_det : 0.0f;
  s.conic[2] = s.valid ? s.a / safe_det : 0.0f;
  const float mid = 0.5f * (s.a + s.c);
  const float disc = mid * mid - safe_det;
  const float lam = mid + PM_SQRT(disc > PM_EIGEN_FLOOR ? disc : PM_EIGEN_FLOOR);
  const float radius = PM_CEIL(PM_SIGMA_EXTENT * PM_SQRT(lam > 0.0f ? lam : 0.0f));
  s.means2d[0] = cam.fx * x / s.zs + cam.cx;
  s.means2d[1] = cam.fy * y / s.zs + cam.cy;
  const bool on_screen = s.means2d[0] + radius > 0.0f && s.means2d[0] - radius < cam.width && s.means2d[1] + radius > 0.0f &&
                         s.means2d[1] - radius < cam.height;
  s.radius = (s.valid && on_screen && PM_ISFINITE(radius)) ? (radius < PM_MAX_RADIUS ? radius : PM_MAX_RADIUS) : 0.0f;
  s.centred = s.in_front && PM_ISFINITE(s.means2d[0]) && PM_ISFINITE(s.means2d[1]);
  if (!s.centred) s.means2d[0] = s.means2d[1] = 0.0f;
  s.depth = z;
  return s;
}

struct PmGrad {
  float mean[3];
  float quat[4];
  float scale[3];
};

// Gradients with respect to the Gaussian's mean, quaternion and scales of a loss whose gradients
// with respect to means2d (g2), conic (gc), depth (gd) and compensation (gk) are given.
inline PmGrad pm_backward(PmCamera cam, PmGaussian g, PmState s, float g2x, float g2y, float gc0, float gc1, float gc2,
                          float gd, float gk) {
  float dp[3] = {0.0f, 0.0f, gd};  // camera-space position
  float dzs = 0.0f;
  if (s.centred) {
    dp[0] += g2x * cam.fx / s.zs;
    dp[1] += g2y * cam.fy / s.zs;
    dzs += -(g2x * cam.fx * s.p[0] + g2y * cam.fy * s.p[1]) / (s.zs * s.zs);
  }
  // blurred Σ2D entries (a, b, c) and the unblurred determinant
  float da = 0.0f, db = 0.0f, dc = 0.0f, ddet_orig = 0.0f;
  if (s.valid) {
    // dK = -K dΣ K (the conic's own expression, as the reference's custom VJP)
    const float A = s.conic[0], B = s.conic[1], C = s.conic[2];
    da = -((gc0 * A) * A + (gc1 * A) * B + (gc2 * B) * B);
    db = -(2.0f * (gc0 * A) * B + gc1 * (A * C + B * B) + 2.0f * (gc2 * B) * C);
    dc = -((gc0 * B) * B + (gc1 * B) * C + (gc2 * C) * C);
  }
  if (cam.antialias && s.live) {
    const float dratio = gk * 0.5f / s.compensation;  // d sqrt(r) = dr / (2 sqrt(r))
    ddet_orig += dratio / s.det;
    const float ddet = -dratio * s.ratio / s.det;
    ddet_orig += ddet;  // det = det_orig + blur (a + c) + blur²
    da += cam.blur * ddet;
    dc += cam.blur * ddet;
  }
  float dt0[3] = {0.0f, 0.0f, 0.0f}, dt1[3] = {0.0f, 0.0f, 0.0f};
  if (s.fits) {
    for (int k = 0; k < 3; ++k) {
      dt0[k] = 2.0f * da * s.t0[k] + db * s.t1[k];
      dt1[k] = db * s.t0[k] + 2.0f * dc * s.t1[k];
    }
  }
  if (ddet_orig != 0.0f) {
    const float m01 = s.t0[0] * s.t1[1] - s.t0[1] * s.t1[0];
    const float m02 = s.t0[0] * s.t1[2] - s.t0[2] * s.t1[0];
    const float m12 = s.t0[1] * s.t1[2] - s.t0[2] * s.t1[1];
    const float g01 = 2.0f * m01 * ddet_orig, g02 = 2.0f * m02 * ddet_orig, g12 = 2.0f * m12 * ddet_orig;
    dt0[0] += g01 * s.t1[1] + g02 * s.t1[2];
    dt0[1] += -g01 * s.t1[0] + g12 * s.t1[2];
    dt0[2] += -g02 * s.t1[0] - g12 * s.t1[1];
    dt1[0] += -g01 * s.t0[1] - g02 * s.t0[2];
    dt1[1] += g01 * s.t0[0] - g12 * s.t0[2];
    dt1[2] += g02 * s.t0[0] + g12 * s.t0[1];
  }
  // T = J L
  float dj00 = 0.0f, dj02 = 0.0f, dj11 = 0.0f, dj12 = 0.0f, dax[9];
  for (int k = 0; k < 3; ++k) {
    dj00 += dt0[k] * s.axes[k];
    dj02 += dt0[k] * s.axes[6 + k];
    dj11 += dt1[k] * s.axes[3 + k];
    dj12 += dt1[k] * s.axes[6 + k];
    dax[k] = dt0[k] * s.j00;
    dax[3 + k] = dt1[k] * s.j11;
    dax[6 + k] = dt0[k] * s.j02 + dt1[k] * s.j12;
  }
  const float zs2 = s.zs * s.zs, zs3 = zs2 * s.zs;
  dzs += -cam.fx / zs2 * dj00 + 2.0f * cam.fx * s.tx / zs3 * dj02 - cam.fy / zs2 * dj11 + 2.0f * cam.fy * s.ty / zs3 * dj12;
  const float dtx = -cam.fx / zs2 * dj02, dty = -cam.fy / zs2 * dj12;
  // tx = zs clip(x / zs): x itself inside the clamp, zs · bound outside it
  if (s.clip_x) dzs += dtx * (s.tx / s.zs); else dp[0] += dtx;
  if (s.clip_y) dzs += dty * (s.ty / s.zs); else dp[1] += dty;
  if (s.in_front) dp[2] += dzs;
  PmGrad out;
  for (int j = 0; j < 3; ++j) out.mean[j] = cam.rot[j] * dp[0] + cam.rot[3 + j] * dp[1] + cam.rot[6 + j] * dp[2];
  // L = R_cam · R(q) · diag(s): dRS = R_camᵀ dL
  float gr[9];
  for (int k = 0; k < 3; ++k) {
    float ds = 0.0f;
    for (int j = 0; j < 3; ++j) {
      const float drs = cam.rot[j] * dax[k] + cam.rot[3 + j] * dax[3 + k] + cam.rot[6 + j] * dax[6 + k];
      gr[3 * j + k] = drs * g.scale[k];
      ds += drs * s.r[3 * j + k];
    }
    out.scale[k] = ds;
  }
  const float w = s.q[0], x = s.q[1], y = s.q[2], z = s.q[3];
  float dq[4];
  dq[0] = 2.0f * (-z * gr[1] + y * gr[2] + z * gr[3] - x * gr[5] - y * gr[6] + x * gr[7]);
  dq[1] = 2.0f * (y * gr[1] + z * gr[2] + y * gr[3] - 2.0f * x * gr[4] - w * gr[5] + z * gr[6] + w * gr[7] - 2.0f * x * gr[8]);
  dq[2] = 2.0f * (-2.0f * y * gr[0] + x * gr[1] + w * gr[2] + x * gr[3] + z * gr[5] - w * gr[6] + z * gr[7] - 2.0f * y * gr[8]);
  dq[3] = 2.0f * (-2.0f * z * gr[0] - w * gr[1] + x * gr[2] + w * gr[3] - 2.0f * z * gr[4] + y * gr[5] + x * gr[6] + y * gr[7]);
  // normalisation q = quat / |quat|: (I - q qᵀ) dq / |quat|
  const float along = w * dq[0] + x * dq[1] + y * dq[2] + z * dq[3];
  for (int i = 0; i < 4; ++i) out.quat[i] = (dq[i] - s.q[i] * along) * s.inv_qnorm;
  return out;
}

#endif  // MLX3D_PROJECTION_MATH_H
