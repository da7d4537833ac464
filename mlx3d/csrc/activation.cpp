// The parameter activations of a training step, exp (log-scales -> scales) and sigmoid (opacity
// logits -> opacities), as a CPU MLX primitive: the kernel library's mlx3d_exp / mlx3d_sigmoid
// (kernels/activation.cpp, mlx3d_kernels.h), threaded over elements, which compute each element with
// MLX's own scalar algorithm, so the results are bitwise those of mx.exp / mx.sigmoid (which run on one
// core); the vjp is MLX's expression, so the gradients are bitwise MLX's too.
#include <nanobind/nanobind.h>
#include <nanobind/stl/string.h>

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

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

enum class Kind { kExp, kSigmoid };

class Activation : public CpuPrimitive {
 public:
  Activation(mx::Stream stream, Kind kind, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use mx.exp / mx.sigmoid"), kind_(kind), num_threads_(num_threads) {}

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const float* x = inputs[0].data<float>();
    float* y = outputs[0].data<float>();
    const int64_t n = inputs[0].size();
    encoder.dispatch([x, y, n, kind = kind_, threads = num_threads_]() {
      check_call(kind == Kind::kExp ? mlx3d_exp(x, n, threads, y) : mlx3d_sigmoid(x, n, threads, y));
    });
  }

  // MLX's Exp and Sigmoid vjps: cot * e^x, and cot * s (1 - s).
  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>& cotangents, const std::vector<int>&,
                             const std::vector<mx::array>& outputs) override {
    auto s = stream();
    const auto& y = outputs[0];
    if (kind_ == Kind::kExp) return {mx::multiply(cotangents[0], y, s)};
    return {mx::multiply(cotangents[0], mx::multiply(y, mx::subtract(mx::array(1.0f, y.dtype()), y, s), s), s)};
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override { return {inputs[0].shape()}; }

  const char* name() const override { return kind_ == Kind::kExp ? "ActivationExp" : "ActivationSigmoid"; }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const Activation*>(&other);
    return o && o->kind_ == kind_ && o->num_threads_ == num_threads_;
  }

 private:
  Kind kind_;
  int num_threads_;
};

mx::array activation(const mx::array& x, const std::string& kind, int num_threads) {
  if (kind != "exp" && kind != "sigmoid") throw std::invalid_argument("activation: kind must be 'exp' or 'sigmoid', got '" + kind + "'");
  if (x.dtype() != mx::float32) throw std::invalid_argument("activation: x must be float32 (the Python wrapper casts it)");
  if (num_threads < 0) throw std::invalid_argument("activation: num_threads must be >= 0 (0 = all cores)");
  auto s = mx::default_stream(mx::Device::cpu);
  return mx::array(x.shape(), mx::float32, std::make_shared<Activation>(s, kind == "exp" ? Kind::kExp : Kind::kSigmoid, num_threads),
                   {mx::contiguous(x, false, s)});
}

}  // namespace

void bind_activation(nb::module_& m) {
  m.def("activation", &activation, "x"_a, "kind"_a, "num_threads"_a = 0,
        "exp(x) (kind 'exp') or sigmoid(x) (kind 'sigmoid') of a float32 array, bitwise as mx.exp / mx.sigmoid\n"
        "(MLX primitive, CPU, threaded; differentiable). Use mlx3d.render.activation.");
}

}  // namespace mlx3d
