// View-dependent colour from spherical harmonics as CPU MLX primitives, threaded over Gaussians.
//
// rgb (N,3) = max(0.5 + Σ_k Y_k(normalise(means - centre)) sh[:, k, :], 0) for the first
// (degree+1)² of the K coefficients (the math, shared with Metal: sh_math.h). The backward
// primitive gives dL/dsh (N,K,3) (zero past the degree) and dL/dmeans (N,3); the centre gets a
// zero gradient. Every Gaussian is computed by one thread from its own inputs only, so results
// are bitwise identical for any thread count.
#include <nanobind/nanobind.h>
#include <nanobind/stl/vector.h>

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
  const float* sh;      // (N, K, 3)
  const float* means;   // (N, 3)
  const float* centre;  // (3,)
  int64_t n;
  int k;
  int degree;
};

ShInputs sh_inputs(const std::vector<mx::array>& inputs, int degree) {
  return {inputs[0].data<float>(), inputs[1].data<float>(), inputs[2].data<float>(), inputs[0].shape(0),
          inputs[0].shape(1), degree};
}

// Unclamped colour of Gaussian i seen along the basis b.
inline void colour_of(const ShInputs& in, int64_t i, const ShBasis& b, float* c) {
  const float* s = in.sh + i * in.k * 3;
  const int bases = sh_num_bases(in.degree);
  for (int ch = 0; ch < 3; ++ch) {
    float acc = b.y[0] * s[ch];
    for (int k = 1; k < bases; ++k) acc = acc + b.y[k] * s[3 * k + ch];
    c[ch] = acc + 0.5f;
  }
}

inline ShDir direction_of(const ShInputs& in, int64_t i) {
  const float* m = in.means + 3 * i;
  return sh_direction(m[0] - in.centre[0], m[1] - in.centre[1], m[2] - in.centre[2]);
}

void run_forward(ShInputs in, int num_threads, float* rgb) {
  parallel_ranges(in.n, num_threads, kBlock, [in, rgb](int64_t lo, int64_t hi) {
    for (int64_t i = lo; i < hi; ++i) {
      const ShDir u = direction_of(in, i);
      const ShBasis b = sh_basis(in.degree, u.x, u.y, u.z);
      float c[3];
      colour_of(in, i, b, c);
      for (int ch = 0; ch < 3; ++ch) rgb[3 * i + ch] = c[ch] > 0.0f ? c[ch] : 0.0f;
    }
  });
}

void run_backward(ShInputs in, const float* cot, int num_threads, float* d_sh, float* d_means) {
  const int bases = sh_num_bases(in.degree);
  parallel_ranges(in.n, num_threads, kBlock, [in, cot, d_sh, d_means, bases](int64_t lo, int64_t hi) {
    for (int64_t i = lo; i < hi; ++i) {
      const ShDir u = direction_of(in, i);
      const ShBasis b = sh_basis(in.degree, u.x, u.y, u.z);
      float c[3], g[3];
      colour_of(in, i, b, c);
      for (int ch = 0; ch < 3; ++ch) g[ch] = c[ch] > 0.0f ? cot[3 * i + ch] : 0.0f;
      const float* s = in.sh + i * in.k * 3;
      float* ds = d_sh + i * in.k * 3;
      float gx = 0.0f, gy = 0.0f, gz = 0.0f;
      for (int k = 0; k < in.k; ++k) {
        float along = 0.0f;  // Σ_c g_c sh[k][c]
        for (int ch = 0; ch < 3; ++ch) {
          ds[3 * k + ch] = k < bases ? g[ch] * b.y[k] : 0.0f;
          along = along + g[ch] * s[3 * k + ch];
        }
        if (k > 0 && k < bases) {
          gx = gx + along * b.dx[k];
          gy = gy + along * b.dy[k];
          gz = gz + along * b.dz[k];
        }
      }
      const ShVec3 d = sh_direction_vjp(u, gx, gy, gz);
      d_means[3 * i] = d.x;
      d_means[3 * i + 1] = d.y;
      d_means[3 * i + 2] = d.z;
    }
  });
}

class ShColorBase : public CpuPrimitive {
 public:
  ShColorBase(mx::Stream stream, int degree, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use the MLX reference, mlx3d.splatting.sh.eval_sh"), degree_(degree), num_threads_(num_threads) {}

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const ShColorBase*>(&other);
    return o && std::string(o->name()) == name() && o->degree_ == degree_ && o->num_threads_ == num_threads_;
  }

 protected:
  int degree_, num_threads_;
};

class ShColorBackward : public ShColorBase {
 public:
  using ShColorBase::ShColorBase;

  // inputs: sh, means, centre, dL/drgb (N,3); outputs: dL/dsh, dL/dmeans
  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    ShInputs in = sh_inputs(inputs, degree_);
    const float* cot = inputs[3].data<float>();
    float* d_sh = outputs[0].data<float>();
    float* d_means = outputs[1].data<float>();
    encoder.dispatch([in, cot, d_sh, d_means, threads = num_threads_]() { run_backward(in, cot, threads, d_sh, d_means); });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error("ShColorBackward: second-order gradients are not implemented.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    return {inputs[0].shape(), inputs[1].shape()};
  }

  const char* name() const override { return "ShColorBackward"; }
};

class ShColorForward : public ShColorBase {
 public:
  using ShColorBase::ShColorBase;

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    ShInputs in = sh_inputs(inputs, degree_);
    float* rgb = outputs[0].data<float>();
    encoder.dispatch([in, rgb, threads = num_threads_]() { run_forward(in, threads, rgb); });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>& primals, const std::vector<mx::array>& cotangents,
                             const std::vector<int>& argnums, const std::vector<mx::array>&) override {
    auto s = stream();
    bool need = false;
    for (int a : argnums) need |= a < 2;
    std::vector<mx::array> grads;
    if (need) {
      auto cot = mx::contiguous(mx::astype(cotangents[0], mx::float32, s), false, s);
      grads = mx::array::make_arrays({primals[0].shape(), primals[1].shape()}, {mx::float32, mx::float32},
                                     std::make_shared<ShColorBackward>(s, degree_, num_threads_),
                                     {primals[0], primals[1], primals[2], cot});
    }
    std::vector<mx::array> result;
    for (int a : argnums) result.push_back(a < 2 ? grads[a] : mx::zeros_like(primals[a], s));
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
mx::array sh_colors(const mx::array& sh, const mx::array& means, const mx::array& centre, int degree, int num_threads) {
  check(degree >= 0 && degree <= 3, "degree must be 0..3, got " + std::to_string(degree));
  check(num_threads >= 0, "num_threads must be >= 0 (0 = all cores), got " + std::to_string(num_threads));
  check(sh.ndim() == 3 && sh.shape(2) == 3, "sh must have shape (N, K, 3), got " + shape_str(sh));
  const int n = sh.shape(0);
  check(sh.shape(1) >= sh_num_bases(degree), "degree " + std::to_string(degree) + " needs K >= " +
                                                   std::to_string(sh_num_bases(degree)) + ", got sh " + shape_str(sh));
  check(means.ndim() == 2 && means.shape(0) == n && means.shape(1) == 3,
        "means must have shape (N, 3) = (" + std::to_string(n) + ", 3), got " + shape_str(means));
  check(centre.ndim() == 1 && centre.shape(0) == 3, "centre must have shape (3,), got " + shape_str(centre));
  for (const auto* a : {&sh, &means, &centre}) check(a->dtype() == mx::float32, "inputs must be float32 (the Python wrapper casts them)");
  auto s = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs;
  for (const auto* a : {&sh, &means, &centre}) inputs.push_back(mx::contiguous(*a, false, s));
  return mx::array({n, 3}, mx::float32, std::make_shared<ShColorForward>(s, degree, num_threads), inputs);
}

}  // namespace

void bind_sh_color(nb::module_& m) {
  m.def("sh_colors", &sh_colors, "sh"_a, "means"_a, "centre"_a, "degree"_a, "num_threads"_a = 0,
        "max(colour, 0) of float32 SH coefficients sh (N,K,3) seen from centre (3,) at means (N,3), up to\n"
        "degree (MLX primitive, CPU, threaded; differentiable w.r.t. sh and means). Use\n"
        "mlx3d.render.sh_color.sh_colors, which dispatches per backend and casts its inputs.");
}

}  // namespace mlx3d
