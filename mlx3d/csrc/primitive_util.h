// Helpers shared by the CPU MLX primitives: output allocation, scratch from MLX's buffer cache, the
// primitives' base class, shape strings; with what every kernel shares (kernels/parallel.h).
#pragma once

#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "kernel_call.h"
#include "kernels/parallel.h"
#include "mlx/allocator.h"
#include "mlx/array.h"
#include "mlx/backend/cpu/encoder.h"
#include "mlx/primitives.h"

namespace mlx3d {

// Uninitialised float scratch from MLX's buffer cache, returned to it on scope exit: reused across
// evaluations, so a kernel's temporaries cost neither fresh pages (faults) nor zeroing per call.
class ScratchFloats {
 public:
  explicit ScratchFloats(size_t n) : data_(mlx::core::allocator::malloc(std::max<size_t>(n, 1) * sizeof(float))) {}
  float* data() { return static_cast<float*>(data_.buffer().raw_ptr()); }

 private:
  mlx::core::allocator::Data data_;
};

// Checks that every input is row-contiguous (the ops make them so before building a primitive, and the
// kernels index them as plain arrays) and registers every array, outputs given their buffers, with the
// primitive's CPU command encoder, which it returns.
inline mlx::core::cpu::CommandEncoder& register_arrays(mlx::core::Primitive& primitive, const std::vector<mlx::core::array>& inputs,
                                                       std::vector<mlx::core::array>& outputs) {
  for (const auto& a : inputs)
    if (!a.flags().row_contiguous) throw std::runtime_error(std::string(primitive.name()) + ": internal error: non-contiguous input");
  auto& encoder = mlx::core::cpu::get_command_encoder(primitive.stream());
  for (const auto& a : inputs) encoder.set_input_array(a);
  for (auto& o : outputs) encoder.set_output_array(o);
  return encoder;
}

// register_arrays, with a fresh buffer for every output.
inline mlx::core::cpu::CommandEncoder& prepare_outputs(mlx::core::Primitive& primitive, const std::vector<mlx::core::array>& inputs,
                                                       std::vector<mlx::core::array>& outputs) {
  for (auto& o : outputs) o.set_data(mlx::core::allocator::malloc(o.nbytes()));
  return register_arrays(primitive, inputs, outputs);
}

// Base of the CPU-only primitives: GPU evaluation, forward-mode differentiation and vmap are refused
// with the primitive's name. `gpu_hint` says what Apple GPUs run instead.
class CpuPrimitive : public mlx::core::Primitive {
 public:
  CpuPrimitive(mlx::core::Stream stream, const char* gpu_hint) : mlx::core::Primitive(stream), gpu_hint_(gpu_hint) {}

  void eval_gpu(const std::vector<mlx::core::array>&, std::vector<mlx::core::array>&) override {
    throw std::runtime_error(std::string(name()) + " runs on the CPU only (" + gpu_hint_ + ").");
  }

  std::vector<mlx::core::array> jvp(const std::vector<mlx::core::array>&, const std::vector<mlx::core::array>&,
                                    const std::vector<int>&) override {
    throw std::runtime_error(std::string(name()) + ": forward-mode differentiation (jvp) is not implemented; use mx.grad / mx.vjp.");
  }

  std::pair<std::vector<mlx::core::array>, std::vector<int>> vmap(const std::vector<mlx::core::array>&,
                                                                  const std::vector<int>&) override {
    throw std::runtime_error(std::string(name()) + ": vmap is not implemented.");
  }

 private:
  const char* gpu_hint_;
};

// "(2, 3)" for a 2x3 array, "(5,)" for a vector.
inline std::string shape_str(const mlx::core::array& a) {
  std::ostringstream os;
  os << "(";
  for (int i = 0; i < static_cast<int>(a.ndim()); ++i) os << (i ? ", " : "") << a.shape(i);
  if (a.ndim() == 1) os << ",";
  os << ")";
  return os.str();
}

}  // namespace mlx3d
