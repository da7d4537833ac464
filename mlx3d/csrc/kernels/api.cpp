// mlx3d_kernels_abi, mlx3d_kernels_build and mlx3d_last_error (mlx3d_kernels.h).
#include <string>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

namespace mlx3d {
namespace {

thread_local std::string last_error;

#define MLX3D_STR2(x) #x
#define MLX3D_STR(x) MLX3D_STR2(x)

std::string build_line() {
  std::string s;
#if defined(__x86_64__) || defined(_M_X64)
  s += "x86_64";
#elif defined(__aarch64__) || defined(_M_ARM64)
  s += "arm64";
#else
  s += "unknown-arch";
#endif
#if defined(_WIN32)
  s += "-windows";
#elif defined(__APPLE__)
  s += "-macos";
#elif defined(__linux__)
  s += "-linux";
#endif
#if defined(__clang__)
  s += " clang " __clang_version__;
#elif defined(__GNUC__)
  s += " gcc " MLX3D_STR(__GNUC__) "." MLX3D_STR(__GNUC_MINOR__);
#elif defined(_MSC_VER)
  s += " msvc " MLX3D_STR(_MSC_VER);
#endif
  s += ", lanes " + std::to_string(kLanes);
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && defined(__linux__)
  s += " (AVX2 variants picked at load)";
#endif
  s += ", ABI " + std::to_string(MLX3D_KERNELS_ABI);
  return s;
}

}  // namespace

void set_last_error(const std::string& message) { last_error = message; }

}  // namespace mlx3d

extern "C" {

MLX3D_API int mlx3d_kernels_abi(void) { return MLX3D_KERNELS_ABI; }

MLX3D_API const char* mlx3d_kernels_build(void) {
  static const std::string line = mlx3d::build_line();
  return line.c_str();
}

MLX3D_API const char* mlx3d_last_error(void) { return mlx3d::last_error.c_str(); }

}  // extern "C"
