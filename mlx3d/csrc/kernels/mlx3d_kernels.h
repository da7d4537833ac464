/* The CPU kernels of mlx3d as a C library: plain functions on raw pointers, sizes and a thread count.
 *
 * One implementation of each kernel, used by the library (libmlx3d_kernels: .so, .dll, .dylib; loaded by
 * mlx3d/kernel_library.py through ctypes on every platform) and by the MLX primitives of mlx3d._core.
 * Conventions, for every function:
 *   - arrays are row-major, contiguous and of the C type in the signature (float: float32, uint8_t: a bool per
 *     byte, 0 or 1); shapes are given in the comments as (N, 3) etc., with N the count argument;
 *   - outputs are written in full (no need to clear them first) and never alias an input, except arrays the
 *     comment says are updated in place;
 *   - threads: worker threads to use, 0 for every hardware thread; results do not depend on it;
 *   - the return value is 0 on success; otherwise the message is in mlx3d_last_error() (this thread's last
 *     failure), and the outputs hold nothing of value.
 * MLX3D_KERNELS_ABI changes whenever a signature or a meaning here does; mlx3d_kernels_abi() returns the
 * value the library was built with, so a loader refuses a library of another version.
 */
#ifndef MLX3D_KERNELS_H
#define MLX3D_KERNELS_H

#include <stdint.h>

#define MLX3D_KERNELS_ABI 1

#if defined(_WIN32)
#define MLX3D_API __declspec(dllexport)
#else
#define MLX3D_API __attribute__((visibility("default")))
#endif

#ifdef __cplusplus
extern "C" {
#endif

MLX3D_API int mlx3d_kernels_abi(void);
/* What the library was built for and with, one line ("x86_64-linux gcc 12.2 lanes 8 ...", for logs). */
MLX3D_API const char* mlx3d_kernels_build(void);
/* The message of this thread's last failed call ("" when none failed). */
MLX3D_API const char* mlx3d_last_error(void);

/* View-dependent colour of N Gaussians from spherical harmonics (sh_math.h):
 *   rgb (N, 3) = max(0.5 + sum_k Y_k(normalise(means - centre)) sh[:, k, :], 0) for k < (degree + 1)^2.
 * The K = k0 + k1 coefficients come as two blocks read as their concatenation along K: block0 (N, k0, 3)
 * and block1 (N, k1, 3) (a model's sh_dc and sh_rest; k1 = 0 and block1 NULL for one array). degree 0..3,
 * K >= (degree + 1)^2. means (N, 3), centre (3,). */
MLX3D_API int mlx3d_sh_forward(const float* block0, int64_t k0, const float* block1, int64_t k1, const float* means,
                               const float* centre, int64_t n, int degree, int threads, float* rgb);
/* Its gradient: from dL/drgb cot (N, 3), dL/dblock0 (N, k0, 3), dL/dblock1 (N, k1, 3) (NULL when k1 = 0; zero
 * past the degree) and dL/dmeans d_means (N, 3). Each Gaussian is computed from its own inputs only, so the
 * results are bitwise the same for any thread count and for one array or two blocks. */
MLX3D_API int mlx3d_sh_backward(const float* block0, int64_t k0, const float* block1, int64_t k1, const float* means,
                                const float* centre, int64_t n, int degree, const float* cot, int threads,
                                float* d_block0, float* d_block1, float* d_means);

/* Adds one view to the densification statistics, float64 (N,) each, in place: where visible (N,),
 * grad_accum += |(grad2d[:, 0] sx, grad2d[:, 1] sy)| (grad2d (N, 2): dL/d(means2d) in pixels; sx, sy = W/2,
 * H/2) and grad_count += 1; max_radii = max(max_radii, radii) (radii int32 (N,); NaN stays). Each operation is
 * rounded as numpy's float64 expression (mlx3d.training.statistics). */
MLX3D_API int mlx3d_add_screen_statistics(const uint8_t* visible, const float* grad2d, const int32_t* radii, int64_t n, double sx,
                                          double sy, double* grad_accum, double* grad_count, double* max_radii, int threads);

/* k nearest neighbours of 3D points with a k-d tree (median split on the widest axis; distances accumulated in
 * double). mlx3d_knn_build: a tree over xyz (n, 3), all finite, leaf_size >= 1, into *tree (free it with
 * mlx3d_knn_free; a tree is read-only, so it may be queried from several threads). mlx3d_knn_info: its point
 * count, leaf size, levels and nodes. mlx3d_knn_order: int64 (n,) the points' indices in tree order (spatially
 * coherent). mlx3d_knn_query: for queries (m, 3) and k: output 0 writes out_index int64 (m, k) and out_dist
 * (m, k) squared distances, sorted by distance (ties by index); 1 the mean Euclidean distance to the k nearest
 * and 2 the distance to the k-th, out_dist (m,) (out_index unused). self_index int64 (m,) or NULL: each query's
 * own point to skip (-1: none). */
MLX3D_API int mlx3d_knn_build(const float* xyz, int64_t n, int leaf_size, void** tree);
MLX3D_API int mlx3d_knn_free(void* tree);
MLX3D_API int mlx3d_knn_info(const void* tree, int64_t* size, int* leaf_size, int* depth, int64_t* node_count);
MLX3D_API int mlx3d_knn_order(const void* tree, int64_t* order);
MLX3D_API int mlx3d_knn_query(const void* tree, const float* queries, int64_t m, int k, const int64_t* self_index, int output,
                              int threads, int64_t* out_index, float* out_dist);

/* ---- rasterizer (raster.cpp) ---- */

/* ---- projection and tile binning (projection.cpp, binning.cpp) ---- */

/* ---- photometric loss (photometric.cpp) ---- */

/* ---- optimizer and activations (adam.cpp, activation.cpp, affine.cpp) ---- */

#ifdef __cplusplus
}
#endif

#endif /* MLX3D_KERNELS_H */
