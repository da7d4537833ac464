// The 3DGS training loss (1 - λ) L1 + λ (1 - SSIM) of an (H,W,C) render against a photo, and its
// gradient with respect to the render, threaded over image rows: mlx3d_photometric_loss; and the mean
// squared error of the per-step PSNR: mlx3d_mse (mlx3d_kernels.h).
//
// SSIM as mlx3d.training.metrics (the 3DGS definition): a separable Gaussian window (the taps
// given), zero-padded "same" filtering of x, y, x², y², xy per channel, C1 = 0.01², C2 = 0.03²,
// the map averaged over channels; with a mask w (H,W) both terms are w-weighted means over pixels.
// The gradient follows from S = A1 A2 / (B1 B2) (A1 = 2 μx μy + C1, A2 = 2 σxy + C2, B1 = μx² +
// μy² + C1, B2 = σx² + σy² + C2): the filter is self-adjoint, so
//   dL/dx = G*(g ∂S/∂μx) + 2x G*(g ∂S/∂E[x²]) + y G*(g ∂S/∂E[xy]) + (1 - λ) w sign(x - y) / (C Σw),
// with g = -λ w / (C Σw) per pixel. The loss and the gradient come from one pass (training always
// needs both). The loss is symmetric in (x, y), so the gradient with respect to the photo is the same
// call with the two swapped. Every output element is computed by one thread, and the loss is summed
// per row then over rows in order (float64), so the results are bitwise identical for any thread count.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>
#include <type_traits>
#include <vector>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

namespace mlx3d {
namespace {

constexpr float kC1 = 0.01f * 0.01f;
constexpr float kC2 = 0.03f * 0.03f;
constexpr double kWeightFloor = 1e-12;
constexpr int kRows = 8;  // at least this many image rows per thread

struct Image {
  int h, w, c;
  size_t size() const { return size_t(h) * w * c; }
};

// The row passes below are also compiled for AVX2 (MLX3D_AVX2_CLONES, parallel.h); F in the
// templates below is float or Lanes (one element or kLanes consecutive ones). Each output
// element is taps[r] * centre, then + taps[k] * (the two elements r - k away) for k = 0 .. r - 1, in that
// order. The passes run over 4 lane groups of a row at a time, whose sums stay in registers over all the
// taps (one store per element instead of one per tap).

// out[j..j + U F) = taps[r] * mid + sum over k of taps[k] * (a_k + d_k) there, where a_k or d_k is null
// outside the image (a zero term, left out).
template <class F, int U>
MLX3D_LANES_INLINE void filter_at(float* out, const float* mid, const float* const* a, const float* const* d,
                                  const float* taps, int r, int j) {
  constexpr int kStep = sizeof(F) / sizeof(float);
  F acc[U];
  for (int u = 0; u < U; ++u) acc[u] = taps[r] * lanes_at<F>(mid + j + u * kStep);
  for (int k = 0; k < r; ++k) {
    const float t = taps[k];
    if (a[k] && d[k])
      for (int u = 0; u < U; ++u) acc[u] += t * (lanes_at<F>(a[k] + j + u * kStep) + lanes_at<F>(d[k] + j + u * kStep));
    else if (a[k])
      for (int u = 0; u < U; ++u) acc[u] += t * lanes_at<F>(a[k] + j + u * kStep);
    else if (d[k])
      for (int u = 0; u < U; ++u) acc[u] += t * lanes_at<F>(d[k] + j + u * kStep);
  }
  for (int u = 0; u < U; ++u) put_lanes(out + j + u * kStep, acc[u]);
}

// filter_at over elements [0, n).
MLX3D_LANES_INLINE void filter_span(float* out, const float* mid, const float* const* a, const float* const* d,
                                    const float* taps, int r, int n) {
  int j = 0;
  for (; j + 4 * kLanes <= n; j += 4 * kLanes) filter_at<Lanes, 4>(out, mid, a, d, taps, r, j);
  for (; j < n; ++j) filter_at<float, 1>(out, mid, a, d, taps, r, j);
}

// Rows [lo, hi) of the vertical pass: tmp = the column filter of src (zero-padded).
MLX3D_AVX2_CLONES void vertical_rows(const float* src, float* tmp, Image im, const float* taps, int r, int64_t lo, int64_t hi) {
  const int rowlen = im.w * im.c;
  std::vector<const float*> a(r), d(r);
  for (int i = int(lo); i < int(hi); ++i) {
    for (int k = 0; k < r; ++k) {
      const int up = i - r + k, down = i + r - k;
      a[k] = up >= 0 ? src + size_t(up) * rowlen : nullptr;
      d[k] = down < im.h ? src + size_t(down) * rowlen : nullptr;
    }
    filter_span(tmp + size_t(i) * rowlen, src + size_t(i) * rowlen, a.data(), d.data(), taps, r, rowlen);
  }
}

// Rows [lo, hi) of the horizontal pass: dst = the row filter of tmp, each row copied into a
// zero-padded scratch row `row` (rowlen + 2 r C floats; branch-free).
MLX3D_AVX2_CLONES void horizontal_rows(const float* tmp, float* dst, float* row, Image im, const float* taps, int r, int64_t lo, int64_t hi) {
  const int rowlen = im.w * im.c, pad = r * im.c;
  std::vector<const float*> a(r), d(r);
  for (int k = 0; k < r; ++k) {
    a[k] = row + k * im.c;            // offset -(r - k) pixels
    d[k] = row + (2 * r - k) * im.c;  // offset +(r - k) pixels
  }
  for (int i = int(lo); i < int(hi); ++i) {
    std::copy(tmp + size_t(i) * rowlen, tmp + size_t(i + 1) * rowlen, row + pad);
    filter_span(dst + size_t(i) * rowlen, row + pad, a.data(), d.data(), taps, r, rowlen);
  }
}

// dst = zero-padded "same" separable filter of src with the symmetric `taps`; tmp: scratch of src's size.
void blur(const float* src, float* dst, float* tmp, Image im, const std::vector<float>& taps, int num_threads) {
  const int r = static_cast<int>(taps.size()) / 2;
  parallel_ranges(im.h, num_threads, kRows, [=](int64_t lo, int64_t hi) {  // taps copied per thread
    vertical_rows(src, tmp, im, taps.data(), r, lo, hi);
  });
  parallel_ranges(im.h, num_threads, kRows, [=](int64_t lo, int64_t hi) {
    std::vector<float> scratch(im.w * im.c + 2 * r * im.c, 0.0f);
    horizontal_rows(tmp, dst, scratch.data(), im, taps.data(), r, lo, hi);
  });
}

struct SsimMaps {
  const float *x, *y, *mu_x, *mu_y, *e_xx, *e_yy, *e_xy;  // (H,W,C): the images and their filtered maps
  float *d_mu, *d_xx, *d_xy;                              // (H,W,C) out: g ∂S/∂μx, g ∂S/∂E[x²], g ∂S/∂E[xy]
};

template <class F>
MLX3D_LANES_INLINE F abs_of(F v) {
#if defined(MLX3D_VECTOR_LANES)
  if constexpr (!std::is_same_v<F, float>) {
    typedef int32_t Bits __attribute__((vector_size(sizeof(F))));
    return (F)((Bits)v & 0x7fffffff);  // fabs per lane: the sign bit cleared
  } else
#endif
    return std::fabs(v);
}

// Element(s) q = base + j of the SSIM map pass: the d_* maps, the SSIM s and |x - y| (to s_row[j],
// l_row[j]), with g = g_row[j].
template <class F>
MLX3D_LANES_INLINE void ssim_element(const SsimMaps& m, const float* g_row, float* s_row, float* l_row, size_t base, int j) {
  const size_t q = base + j;
  const F m1 = lanes_at<F>(m.mu_x + q), m2 = lanes_at<F>(m.mu_y + q);
  const F s11 = lanes_at<F>(m.e_xx + q) - m1 * m1, s22 = lanes_at<F>(m.e_yy + q) - m2 * m2;
  const F s12 = lanes_at<F>(m.e_xy + q) - m1 * m2;
  const F a1 = 2.0f * m1 * m2 + kC1, a2 = 2.0f * s12 + kC2;
  const F b1 = m1 * m1 + m2 * m2 + kC1, b2 = s11 + s22 + kC2;
  const F den = b1 * b2, s = a1 * a2 / den;
  const F ds_a1 = a2 / den, ds_a2 = a1 / den, ds_b1 = -s / b1, ds_b2 = -s / b2;
  const F g = lanes_at<F>(g_row + j);
  put_lanes(s_row + j, s);
  put_lanes(l_row + j, abs_of(lanes_at<F>(m.x + q) - lanes_at<F>(m.y + q)));
  put_lanes(m.d_mu + q, g * (ds_a1 * 2.0f * m2 - ds_a2 * 2.0f * m2 + ds_b1 * 2.0f * m1 - ds_b2 * 2.0f * m1));
  put_lanes(m.d_xx + q, g * ds_b2);
  put_lanes(m.d_xy + q, g * 2.0f * ds_a2);
}

// Row i of the SSIM map pass: the d_* maps of its elements, and the row's w-weighted sums of the
// per-pixel L1 and SSIM (each the mean over channels). The elements run in lanes; each pixel's channel
// sums and the row's float64 sums are then taken in order, so the results do not depend on the lanes.
// scratch: 3 W C floats.
MLX3D_AVX2_CLONES void ssim_row(const SsimMaps& m, const float* w, Image im, float lambda, double inv_w, int i,
                                float* scratch, double& row_l1, double& row_ssim) {
  const int rowlen = im.w * im.c;
  const size_t base = size_t(i) * rowlen;
  const float inv_c = 1.0f / im.c;
  float *g_row = scratch, *s_row = scratch + rowlen, *l_row = scratch + 2 * rowlen;
  for (int xj = 0; xj < im.w; ++xj) {
    const float wp = w ? w[size_t(i) * im.w + xj] : 1.0f;
    const float g = static_cast<float>(-lambda * wp * inv_w) * inv_c;
    for (int ch = 0; ch < im.c; ++ch) g_row[xj * im.c + ch] = g;
  }
  int j = 0;
  for (; j + kLanes <= rowlen; j += kLanes) ssim_element<Lanes>(m, g_row, s_row, l_row, base, j);
  for (; j < rowlen; ++j) ssim_element<float>(m, g_row, s_row, l_row, base, j);
  double l1 = 0.0, ssim = 0.0;
  for (int xj = 0; xj < im.w; ++xj) {
    const float wp = w ? w[size_t(i) * im.w + xj] : 1.0f;
    float sp = 0.0f, lp = 0.0f;
    for (int ch = 0; ch < im.c; ++ch) {
      sp += s_row[xj * im.c + ch];
      lp += l_row[xj * im.c + ch];
    }
    l1 += double(wp) * (lp * inv_c);
    ssim += double(wp) * (sp * inv_c);
  }
  row_l1 = l1;
  row_ssim = ssim;
}


// loss (one float) and dL/dx (H,W,C) of x against y, weights w (H,W) or null; scratch: 8 H W C floats.
void run_loss(const float* x, const float* y, const float* w, Image im, float lambda, const std::vector<float>& taps,
              int num_threads, float* scratch, float* loss_out, float* grad) {
  const size_t n = im.size();
  const int pixels = im.h * im.w;
  const int64_t per_thread = int64_t(kRows) * im.w * im.c;  // elements: as many threads as for the rows
  double wsum = 0.0;
  if (w)
    for (int p = 0; p < pixels; ++p) wsum += w[p];
  else
    wsum = pixels;
  const double inv_w = 1.0 / std::max(wsum, kWeightFloor);
  // (H,W,C) each, each fully written before it is read
  float *prod = scratch, *tmp = scratch + n, *mu_x = scratch + 2 * n, *mu_y = scratch + 3 * n, *e_xx = scratch + 4 * n,
        *e_yy = scratch + 5 * n, *e_xy = scratch + 6 * n, *d_xy = scratch + 7 * n;
  auto fill = [&](auto f) {
    float* out = prod;
    parallel_blocks(int64_t(n), num_threads, per_thread, [=](int64_t lo, int64_t hi) {
      for (int64_t i = lo; i < hi; ++i) out[i] = f(i);
    });
  };
  blur(x, mu_x, tmp, im, taps, num_threads);
  blur(y, mu_y, tmp, im, taps, num_threads);
  fill([x](int64_t i) { return x[i] * x[i]; });
  blur(prod, e_xx, tmp, im, taps, num_threads);
  fill([y](int64_t i) { return y[i] * y[i]; });
  blur(prod, e_yy, tmp, im, taps, num_threads);
  fill([x, y](int64_t i) { return x[i] * y[i]; });
  blur(prod, e_xy, tmp, im, taps, num_threads);
  // per pixel: the loss terms, and g ∂S/∂(μx, E[x²], E[xy]) in place of prod and tmp, and in d_xy
  std::vector<double> row_l1(im.h, 0.0), row_ssim(im.h, 0.0);
  float* d_mu = prod;
  float* d_xx = tmp;
  const SsimMaps maps{x, y, mu_x, mu_y, e_xx, e_yy, e_xy, d_mu, d_xx, d_xy};
  parallel_ranges(im.h, num_threads, kRows, [=, row_l1 = row_l1.data(), row_ssim = row_ssim.data()](int64_t lo, int64_t hi) {
    std::vector<float> scratch(3 * size_t(im.w) * im.c);
    for (int i = int(lo); i < int(hi); ++i) ssim_row(maps, w, im, lambda, inv_w, i, scratch.data(), row_l1[i], row_ssim[i]);
  });
  double l1 = 0.0, ssim = 0.0;
  for (int i = 0; i < im.h; ++i) l1 += row_l1[i], ssim += row_ssim[i];
  const float inv_c = 1.0f / im.c;
  *loss_out = static_cast<float>((1.0 - lambda) * l1 * inv_w + lambda * (1.0 - ssim * inv_w));
  // back through the filter (self-adjoint); mu_x, e_xx, e_xy are free now
  blur(d_mu, mu_x, e_yy, im, taps, num_threads);
  blur(d_xx, e_xx, e_yy, im, taps, num_threads);
  blur(d_xy, e_xy, e_yy, im, taps, num_threads);
  const float l1_scale = static_cast<float>((1.0 - lambda) * inv_w) * inv_c;
  parallel_blocks(int64_t(n), num_threads, per_thread, [=](int64_t lo, int64_t hi) {
    for (int64_t q = lo; q < hi; ++q) {
      const float diff = x[q] - y[q];
      const float sign = diff > 0.0f ? 1.0f : (diff < 0.0f ? -1.0f : 0.0f);
      const float wp = w ? w[q / im.c] : 1.0f;
      grad[q] = mu_x[q] + 2.0f * x[q] * e_xx[q] + y[q] * e_xy[q] + l1_scale * wp * sign;
    }
  });
}

// The mean squared error of x, clipped to [0, 1] when `clip`, against y: the mean over channels of
// each pixel's squared differences, then the mean over pixels (w-weighted when w is given, divided by
// max(sum w, 1e-12)), as mlx3d.training.metrics.mse with the image clipped first. Rows are summed in
// float64 on threads, then in row order, so the result does not depend on the thread count.
float run_mse(const float* x, const float* y, const float* w, Image im, bool clip, int num_threads) {
  std::vector<double> rows(im.h, 0.0), weights(im.h, 0.0);
  parallel_ranges(im.h, num_threads, kRows, [=, rows = rows.data(), weights = weights.data()](int64_t lo, int64_t hi) {
    const float inv_c = 1.0f / im.c;
    for (int i = int(lo); i < int(hi); ++i) {
      double sum = 0.0, wsum = 0.0;
      for (int xj = 0; xj < im.w; ++xj) {
        const size_t q = (size_t(i) * im.w + xj) * im.c;
        float sq = 0.0f;
        for (int ch = 0; ch < im.c; ++ch) {
          const float v = clip ? std::min(std::max(x[q + ch], 0.0f), 1.0f) : x[q + ch];
          const float d = v - y[q + ch];
          sq += d * d;
        }
        const double wp = w ? w[size_t(i) * im.w + xj] : 1.0;
        sum += wp * (sq * inv_c);
        wsum += wp;
      }
      rows[i] = sum;
      weights[i] = wsum;
    }
  });
  double sum = 0.0, wsum = 0.0;
  for (int i = 0; i < im.h; ++i) sum += rows[i], wsum += weights[i];
  return static_cast<float>(sum / std::max(wsum, kWeightFloor));
}

// The image size checked (H, W, C >= 1, H W C < 2^31: the kernels index rows and pixels with int).
Image image_of(int64_t h, int64_t w, int64_t c) {
  require(h >= 1 && w >= 1 && c >= 1, "the image must be (H, W, C) with H, W, C >= 1, got (" + std::to_string(h) + ", " +
                                           std::to_string(w) + ", " + std::to_string(c) + ")");
  require(h <= INT32_MAX / w && h * w <= INT32_MAX / c, "the image must hold fewer than 2^31 values, got (" + std::to_string(h) + ", " +
                                                            std::to_string(w) + ", " + std::to_string(c) + ")");
  return {int(h), int(w), int(c)};
}

}  // namespace
}  // namespace mlx3d

extern "C" {

MLX3D_API int mlx3d_photometric_loss(const float* x, const float* y, const float* weights, int64_t h, int64_t w, int64_t c,
                                     float lambda, const float* taps, int64_t ntaps, int threads, float* scratch, float* loss,
                                     float* grad) {
  return mlx3d::guarded("mlx3d_photometric_loss", [&] {
    const mlx3d::Image im = mlx3d::image_of(h, w, c);
    mlx3d::require(ntaps >= 1 && ntaps % 2 == 1, "taps must have an odd, positive length, got " + std::to_string(ntaps));
    mlx3d::require(ntaps - 1 <= (INT32_MAX - w * c) / c, "too many taps (" + std::to_string(ntaps) + ") for rows of " +
                                                             std::to_string(w * c) + " values");
    mlx3d::require(lambda >= 0.0f && lambda <= 1.0f, "lambda must be in [0, 1], got " + std::to_string(lambda));
    mlx3d::require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
    mlx3d::require(x && y && taps && loss && grad, "a null pointer (only weights and scratch may be NULL)");
    const std::vector<float> filter(taps, taps + ntaps);
    if (scratch) {
      mlx3d::run_loss(x, y, weights, im, lambda, filter, threads, scratch, loss, grad);
    } else {
      mlx3d::HugePageArray<float> own(8 * im.size());
      mlx3d::run_loss(x, y, weights, im, lambda, filter, threads, own.data(), loss, grad);
    }
  });
}

MLX3D_API int mlx3d_mse(const float* x, const float* y, const float* weights, int64_t h, int64_t w, int64_t c, int clip, int threads,
                        float* out) {
  return mlx3d::guarded("mlx3d_mse", [&] {
    const mlx3d::Image im = mlx3d::image_of(h, w, c);
    mlx3d::require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
    mlx3d::require(x && y && out, "a null pointer (only weights may be NULL)");
    *out = mlx3d::run_mse(x, y, weights, im, clip != 0, threads);
  });
}

}  // extern "C"
