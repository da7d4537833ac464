// View-dependent colour from spherical harmonics as CPU MLX primitives, threaded over Gaussians.
//
// rgb (N,3) = max(0.5 + Σ_k Y_k(normalise(means - centre)) sh[:, k, :], 0) for the first
// (degree+1)² of the K coefficients (the math, shared with Metal: sh_math.h). The coefficients come
// as one (N,K,3) array or as two blocks (N,K0,3), (N,K1,3) with K = K0 + K1 (a model's sh_dc and
// sh_rest, read in place instead of concatenated). The backward primitive gives dL/d(each block)
// (zero past the degree) and dL/dmeans (N,3); the centre gets a zero gradient. Every Gaussian is
// computed by one thread from its own inputs only, so results are bitwise identical for any thread
// count, and for one array or two blocks.
#include <nanobind/nanobind.h>
#include <nanobind/stl/vector.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "bindings.h"
#include "mlx/array.h"
#include "mlx/ops.h"
#include "mlx/primitives.h"
#include "primitive_util.h"
#include "sh_math.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

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

// inputs: the 1 or 2 coefficient blocks, means, centre (then anything else, unread).
ShInputs sh_inputs(const std::vector<mx::array>& inputs, int blocks, int degree) {
  ShInputs in{};
  for (int b = 0; b < blocks; ++b) {
    in.block[b] = inputs[b].data<float>();
    in.kb[b] = inputs[b].shape(1);
  }
  in.means = inputs[blocks].data<float>();
  in.centre = inputs[blocks + 1].data<float>();
  in.n = inputs[0].shape(0);
  in.k = in.kb[0] + in.kb[1];
  in.degree = degree;
  return in;
}

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

class ShColorBase : public CpuPrimitive {
 public:
  ShColorBase(mx::Stream stream, int blocks, int degree, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use the MLX reference, mlx3d.splatting.sh.eval_sh"),
        blocks_(blocks), degree_(degree), num_threads_(num_threads) {}

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const ShColorBase*>(&other);
    return o && std::string(o->name()) == name() && o->blocks_ == blocks_ && o->degree_ == degree_ && o->num_threads_ == num_threads_;
  }

 protected:
  int blocks_, degree_, num_threads_;
};

class ShColorBackward : public ShColorBase {
 public:
  using ShColorBase::ShColorBase;

  // inputs: the coefficient blocks, means, centre, dL/drgb (N,3); outputs: dL/d(each block), dL/dmeans
  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    ShInputs in = sh_inputs(inputs, blocks_, degree_);
    const float* cot = inputs[blocks_ + 2].data<float>();
    float* d_block[2] = {outputs[0].data<float>(), blocks_ > 1 ? outputs[1].data<float>() : nullptr};
    float* d_means = outputs[blocks_].data<float>();
    encoder.dispatch([in, cot, d_block, d_means, threads = num_threads_]() { run_backward(in, cot, threads, d_block, d_means); });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error("ShColorBackward: second-order gradients are not implemented.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    std::vector<mx::Shape> shapes;
    for (int b = 0; b <= blocks_; ++b) shapes.push_back(inputs[b].shape());  // the blocks, then means
    return shapes;
  }

  const char* name() const override { return "ShColorBackward"; }
};

class ShColorForward : public ShColorBase {
 public:
  using ShColorBase::ShColorBase;

  // inputs: the coefficient blocks, means, centre
  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    ShInputs in = sh_inputs(inputs, blocks_, degree_);
    float* rgb = outputs[0].data<float>();
    encoder.dispatch([in, rgb, threads = num_threads_]() { run_forward(in, threads, rgb); });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>& primals, const std::vector<mx::array>& cotangents,
                             const std::vector<int>& argnums, const std::vector<mx::array>&) override {
    auto s = stream();
    const int centre = blocks_ + 1;  // primals: blocks, means, centre
    bool need = false;
    for (int a : argnums) need |= a < centre;
    std::vector<mx::array> grads;
    if (need) {
      auto cot = mx::contiguous(mx::astype(cotangents[0], mx::float32, s), false, s);
      std::vector<mx::array> inputs(primals.begin(), primals.end());
      inputs.push_back(cot);
      std::vector<mx::Shape> shapes;
      for (int b = 0; b < centre; ++b) shapes.push_back(primals[b].shape());
      grads = mx::array::make_arrays(shapes, std::vector<mx::Dtype>(shapes.size(), mx::float32),
                                     std::make_shared<ShColorBackward>(s, blocks_, degree_, num_threads_), inputs);
    }
    std::vector<mx::array> result;
    for (int a : argnums) result.push_back(a < centre ? grads[a] : mx::zeros_like(primals[a], s));
    return result;
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    return {{inputs[0].shape(0), 3}};
  }

  const char* name() const override { return "ShColorForward"; }
};

void check(bool ok, const std::string& msg) {
  if (!ok) throw std::invalid_argument("sh_colors: " + msg);
}

// The op: validates shapes/dtypes, makes the inputs row-contiguous, returns rgb (N,3), lazily evaluated.
// sh: the coefficients as [(N,K,3)] or [(N,K0,3), (N,K1,3)] (K = K0 + K1, K0 >= 1).
mx::array sh_colors(const std::vector<mx::array>& sh, const mx::array& means, const mx::array& centre, int degree, int num_threads) {
  check(degree >= 0 && degree <= 3, "degree must be 0..3, got " + std::to_string(degree));
  check(num_threads >= 0, "num_threads must be >= 0 (0 = all cores), got " + std::to_string(num_threads));
  check(sh.size() == 1 || sh.size() == 2, "sh must be one (N, K, 3) array or two blocks, got " + std::to_string(sh.size()) + " arrays");
  check(sh[0].ndim() == 3 && sh[0].shape(2) == 3 && sh[0].shape(1) >= 1, "sh must have shape (N, K, 3) with K >= 1, got " + shape_str(sh[0]));
  const int n = sh[0].shape(0);
  int k = 0;
  for (const auto& b : sh) {
    check(b.ndim() == 3 && b.shape(0) == n && b.shape(2) == 3,
          "every sh block must have shape (" + std::to_string(n) + ", K, 3), got " + shape_str(b));
    k += b.shape(1);
  }
  check(k >= sh_num_bases(degree), "degree " + std::to_string(degree) + " needs K >= " + std::to_string(sh_num_bases(degree)) +
                                       " coefficients, got " + std::to_string(k));
  check(means.ndim() == 2 && means.shape(0) == n && means.shape(1) == 3,
        "means must have shape (N, 3) = (" + std::to_string(n) + ", 3), got " + shape_str(means));
  check(centre.ndim() == 1 && centre.shape(0) == 3, "centre must have shape (3,), got " + shape_str(centre));
  check(means.dtype() == mx::float32 && centre.dtype() == mx::float32, "inputs must be float32 (the Python wrapper casts them)");
  for (const auto& b : sh) check(b.dtype() == mx::float32, "inputs must be float32 (the Python wrapper casts them)");
  auto s = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs;
  for (const auto& b : sh) inputs.push_back(mx::contiguous(b, false, s));
  for (const auto* a : {&means, &centre}) inputs.push_back(mx::contiguous(*a, false, s));
  return mx::array({n, 3}, mx::float32, std::make_shared<ShColorForward>(s, static_cast<int>(sh.size()), degree, num_threads), inputs);
}

}  // namespace

void bind_sh_color(nb::module_& m) {
  m.def("sh_colors", &sh_colors, "sh"_a, "means"_a, "centre"_a, "degree"_a, "num_threads"_a = 0,
        "max(colour, 0) of float32 SH coefficients seen from centre (3,) at means (N,3), up to degree;\n"
        "sh: [(N,K,3)] or two blocks [(N,K0,3), (N,K1,3)] read as their concatenation (MLX primitive,\n"
        "CPU, threaded; differentiable w.r.t. the blocks and means). Use\n"
        "mlx3d.render.sh_color.sh_colors, which dispatches per backend and casts its inputs.");
}

}  // namespace mlx3d
