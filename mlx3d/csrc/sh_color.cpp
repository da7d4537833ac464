// View-dependent colour from spherical harmonics as CPU MLX primitives: the kernel library's
// mlx3d_sh_forward / mlx3d_sh_backward (kernels/sh.cpp, mlx3d_kernels.h) run on MLX arrays.
//
// The coefficients come as one (N,K,3) array or as two blocks (N,K0,3), (N,K1,3) with K = K0 + K1 (a
// model's sh_dc and sh_rest, read in place instead of concatenated). The backward primitive gives
// dL/d(each block) (zero past the degree) and dL/dmeans (N,3); the centre gets a zero gradient.
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
#include "kernels/mlx3d_kernels.h"
#include "primitive_util.h"
#include "sh_math.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

// The 1 or 2 coefficient blocks of `inputs` (then means, centre): their pointers and coefficient counts.
struct ShBlocks {
  const float* block[2] = {nullptr, nullptr};
  int64_t k[2] = {0, 0};
};

ShBlocks sh_blocks(const std::vector<mx::array>& inputs, int blocks) {
  ShBlocks b;
  for (int i = 0; i < blocks; ++i) {
    b.block[i] = inputs[i].data<float>();
    b.k[i] = inputs[i].shape(1);
  }
  return b;
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
    const ShBlocks b = sh_blocks(inputs, blocks_);
    const float* means = inputs[blocks_].data<float>();
    const float* centre = inputs[blocks_ + 1].data<float>();
    const float* cot = inputs[blocks_ + 2].data<float>();
    float* d_block1 = blocks_ > 1 ? outputs[1].data<float>() : nullptr;
    float* d_block0 = outputs[0].data<float>();
    float* d_means = outputs[blocks_].data<float>();
    const int64_t n = inputs[0].shape(0);
    encoder.dispatch([=, degree = degree_, threads = num_threads_]() {
      check_call(mlx3d_sh_backward(b.block[0], b.k[0], b.block[1], b.k[1], means, centre, n, degree, cot, threads, d_block0, d_block1, d_means));
    });
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
    const ShBlocks b = sh_blocks(inputs, blocks_);
    const float* means = inputs[blocks_].data<float>();
    const float* centre = inputs[blocks_ + 1].data<float>();
    float* rgb = outputs[0].data<float>();
    const int64_t n = inputs[0].shape(0);
    encoder.dispatch([=, degree = degree_, threads = num_threads_]() {
      check_call(mlx3d_sh_forward(b.block[0], b.k[0], b.block[1], b.k[1], means, centre, n, degree, threads, rgb));
    });
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
