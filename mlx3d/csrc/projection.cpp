// EWA projection of 3D Gaussians as CPU MLX primitives: the kernel library's mlx3d_project_ewa and
// mlx3d_project_ewa_backward (kernels/projection.cpp, mlx3d_kernels.h) run on MLX arrays.
//
// Forward: means (N,3), quats (N,4), scales (N,3) -> means2d (N,2), conics (N,3), radii (N,) int32,
// depths (N,), compensation (N,). Backward: the gradients of means, quats and scales from those of
// means2d, conics, depths and compensation (radii have none).
#include <nanobind/nanobind.h>
#include <nanobind/stl/vector.h>

#include <algorithm>
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

// The camera as mlx3d_project_ewa takes it.
struct EwaCamera {
  float viewmat[16];  // world-to-camera, row-major
  float fx, fy, cx, cy;
  int width, height;
  float near_z, far_z, blur;
  int antialias;

  bool operator==(const EwaCamera& o) const {
    for (int i = 0; i < 12; ++i)  // the last row is not read
      if (viewmat[i] != o.viewmat[i]) return false;
    return fx == o.fx && fy == o.fy && cx == o.cx && cy == o.cy && width == o.width && height == o.height &&
           near_z == o.near_z && far_z == o.far_z && blur == o.blur && antialias == o.antialias;
  }
};

class ProjectBase : public CpuPrimitive {
 public:
  ProjectBase(mx::Stream stream, EwaCamera cam, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use the MLX reference projection"), cam_(cam), num_threads_(num_threads) {}

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const ProjectBase*>(&other);
    return o && std::string(o->name()) == name() && o->num_threads_ == num_threads_ && o->cam_ == cam_;
  }

 protected:
  EwaCamera cam_;
  int num_threads_;
};

class ProjectEwaBackward : public ProjectBase {
 public:
  using ProjectBase::ProjectBase;

  // inputs: means, quats, scales, dL/dmeans2d (N,2), dL/dconics (N,3), dL/ddepths (N,), dL/dcompensation (N,)
  // outputs: dL/dmeans, dL/dquats, dL/dscales
  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const float* in[7];
    for (int k = 0; k < 7; ++k) in[k] = inputs[k].data<float>();
    float *d_means = outputs[0].data<float>(), *d_quats = outputs[1].data<float>(), *d_scales = outputs[2].data<float>();
    const int64_t n = inputs[0].shape(0);
    encoder.dispatch([=, c = cam_, threads = num_threads_]() {
      check_call(mlx3d_project_ewa_backward(in[0], in[1], in[2], n, c.viewmat, c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.near_z,
                                            c.far_z, c.blur, c.antialias, in[3], in[4], in[5], in[6], threads, d_means, d_quats,
                                            d_scales));
    });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error("ProjectEwaBackward: second-order gradients are not implemented.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    return {inputs[0].shape(), inputs[1].shape(), inputs[2].shape()};
  }

  const char* name() const override { return "ProjectEwaBackward"; }
};

class ProjectEwaForward : public ProjectBase {
 public:
  using ProjectBase::ProjectBase;

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const float *means = inputs[0].data<float>(), *quats = inputs[1].data<float>(), *scales = inputs[2].data<float>();
    float *means2d = outputs[0].data<float>(), *conics = outputs[1].data<float>(), *depths = outputs[3].data<float>(),
          *compensation = outputs[4].data<float>();
    int32_t* radii = outputs[2].data<int32_t>();
    const int64_t n = inputs[0].shape(0);
    encoder.dispatch([=, c = cam_, threads = num_threads_]() {
      check_call(mlx3d_project_ewa(means, quats, scales, n, c.viewmat, c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.near_z, c.far_z,
                                   c.blur, c.antialias, threads, means2d, conics, radii, depths, compensation));
    });
  }

  // Cotangents: one per output (means2d, conics, radii, depths, compensation); radii's is ignored.
  std::vector<mx::array> vjp(const std::vector<mx::array>& primals, const std::vector<mx::array>& cotangents,
                             const std::vector<int>& argnums, const std::vector<mx::array>&) override {
    auto s = stream();
    auto prep = [&](const mx::array& x) { return mx::contiguous(mx::astype(x, mx::float32, s), false, s); };
    auto grads = mx::array::make_arrays({primals[0].shape(), primals[1].shape(), primals[2].shape()}, {mx::float32, mx::float32, mx::float32},
                                        std::make_shared<ProjectEwaBackward>(s, cam_, num_threads_),
                                        {primals[0], primals[1], primals[2], prep(cotangents[0]), prep(cotangents[1]),
                                         prep(cotangents[3]), prep(cotangents[4])});
    std::vector<mx::array> result;
    for (int a : argnums) result.push_back(grads[a]);
    return result;
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    const int n = inputs[0].shape(0);
    return {{n, 2}, {n, 3}, {n}, {n}, {n}};
  }

  const char* name() const override { return "ProjectEwaForward"; }
};

void check(bool ok, const std::string& msg) {
  if (!ok) throw std::invalid_argument("project_ewa: " + msg);
}

std::vector<mx::array> project_ewa(const mx::array& means, const mx::array& quats, const mx::array& scales, const std::vector<float>& viewmat,
                                   float fx, float fy, float cx, float cy, int width, int height, float near_z, float far_z,
                                   float blur, bool antialias, int num_threads) {
  check(means.ndim() == 2 && means.shape(1) == 3, "means must have shape (N, 3), got " + shape_str(means));
  const int n = means.shape(0);
  check(quats.ndim() == 2 && quats.shape(0) == n && quats.shape(1) == 4,
        "quats must have shape (N, 4) = (" + std::to_string(n) + ", 4), got " + shape_str(quats));
  check(scales.ndim() == 2 && scales.shape(0) == n && scales.shape(1) == 3,
        "scales must have shape (N, 3) = (" + std::to_string(n) + ", 3), got " + shape_str(scales));
  for (const auto* a : {&means, &quats, &scales}) check(a->dtype() == mx::float32, "inputs must be float32 (the Python wrapper casts them)");
  check(viewmat.size() == 16, "viewmat must have 16 entries (4x4 row-major)");
  check(width >= 1 && height >= 1, "width and height must be >= 1");
  check(num_threads >= 0, "num_threads must be >= 0 (0 = all cores)");
  EwaCamera cam;
  std::copy(viewmat.begin(), viewmat.end(), cam.viewmat);
  cam.fx = fx, cam.fy = fy, cam.cx = cx, cam.cy = cy, cam.width = width, cam.height = height;
  cam.near_z = near_z, cam.far_z = far_z, cam.blur = blur, cam.antialias = antialias ? 1 : 0;
  auto s = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs;
  for (const auto* a : {&means, &quats, &scales}) inputs.push_back(mx::contiguous(*a, false, s));
  return mx::array::make_arrays({{n, 2}, {n, 3}, {n}, {n}, {n}}, {mx::float32, mx::float32, mx::int32, mx::float32, mx::float32},
                                std::make_shared<ProjectEwaForward>(s, cam, num_threads), inputs);
}

}  // namespace

void bind_projection(nb::module_& m) {
  m.def("project_ewa", &project_ewa, "means"_a, "quats"_a, "scales"_a, "viewmat"_a, "fx"_a, "fy"_a, "cx"_a, "cy"_a, "width"_a,
        "height"_a, "near"_a, "far"_a, "blur"_a = 0.3f, "antialias"_a = false, "num_threads"_a = 0,
        "EWA projection (MLX primitive, CPU, threaded; differentiable w.r.t. means, quats, scales):\n"
        "returns [means2d (N,2), conics (N,3), radii (N,) int32, depths (N,), compensation (N,)].\n"
        "Use mlx3d.render.projection.project_ewa, which validates and casts its inputs.");
}

}  // namespace mlx3d
