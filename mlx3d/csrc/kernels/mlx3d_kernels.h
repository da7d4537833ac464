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
 *   - the return value is 0 on success, 2 when an argument is invalid and 1 on any other failure; the message is
 *     then in mlx3d_last_error() (this thread's last failure), and the outputs hold nothing of value.
 * MLX3D_KERNELS_ABI changes whenever a signature or a meaning here does; mlx3d_kernels_abi() returns the
 * value the library was built with, so a loader refuses a library of another version.
 */
#ifndef MLX3D_KERNELS_H
#define MLX3D_KERNELS_H

#include <stdint.h>

#define MLX3D_KERNELS_ABI 2

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
/* The 3DGS tile rasterizer (raster.cpp; per-pixel rules: raster_math.h, docs/guides/rendering.md): N Gaussians
 * means2d (N, 2) pixels, conics (N, 3) (a, b, c of the inverse 2D covariance [[a, b], [b, c]], 1/pixels^2),
 * features (N, C), opacities (N,), binned into tiles of tile_size pixels: tile_offsets int32 (tiles + 1,), tile
 * t's entries flatten_ids[tile_offsets[t] .. tile_offsets[t + 1]) (int32 Gaussian indices, front to back; M
 * entries), tiles = ceil(W / tile_size) ceil(H / tile_size) in row-major order. Composited front to back per
 * pixel: accum (H, W, C), alpha (H, W) = 1 - final_T, last int32 (H, W) (1 + the position in the tile's range
 * of the last Gaussian that contributed, 0 for none), final_T (H, W). background (C,) or NULL: accum += (1 -
 * alpha) background. The results do not depend on threads; the backward pass's, in their last bits, on the
 * lane width (mlx3d_rasterizer_lanes). */
MLX3D_API int mlx3d_rasterize_forward(const float* means2d, const float* conics, const float* features, const float* opacities,
                                      const int32_t* tile_offsets, const int32_t* flatten_ids, int64_t n, int channels, int64_t m,
                                      int width, int height, int tile_size, const float* background, int threads, float* accum,
                                      float* alpha, int32_t* last, float* final_T);
/* The forward pass composited in depth order with a per-pixel surface layer (forward only): depths (N,) the
 * Gaussians' camera z (the binning's sort key), surface_color (H, W, C) premultiplied, surface_alpha (H, W),
 * surface_depth (H, W) camera z (+inf: behind every Gaussian). */
MLX3D_API int mlx3d_rasterize_forward_surface(const float* means2d, const float* conics, const float* features,
                                              const float* opacities, const int32_t* tile_offsets, const int32_t* flatten_ids,
                                              int64_t n, int channels, int64_t m, int width, int height, int tile_size,
                                              const float* depths, const float* surface_color, const float* surface_alpha,
                                              const float* surface_depth, int threads, float* accum, float* alpha, int32_t* last,
                                              float* final_T);
/* The forward pass's vector-Jacobian product: from its inputs, its last and final_T, and dL/daccum d_accum
 * (H, W, C), dL/dalpha d_alpha (H, W) (and the forward's background, or NULL): d_means2d (N, 2), d_conics (N, 3),
 * d_features (N, C), d_opacities (N,). Summed per tile entry, then per Gaussian in flatten_ids order: the same
 * bits for any thread count. */
MLX3D_API int mlx3d_rasterize_backward(const float* means2d, const float* conics, const float* features, const float* opacities,
                                       const int32_t* tile_offsets, const int32_t* flatten_ids, int64_t n, int channels, int64_t m,
                                       int width, int height, int tile_size, const int32_t* last, const float* final_T,
                                       const float* d_accum, const float* d_alpha, const float* background, int threads,
                                       float* d_means2d, float* d_conics, float* d_features, float* d_opacities);
/* Pixels the tile kernels run at once on this CPU: 8 (AVX2, x86-64 Linux builds), 4 (SSE2, NEON), 1 (scalar).
 * MLX3D_RASTER_ISA=baseline in the environment forces the baseline variant; MLX3D_RASTER_CULL=0 turns off the
 * sub-tile culling (the same results; for tests). */
MLX3D_API int mlx3d_rasterizer_lanes(void);

/* ---- projection and tile binning (projection.cpp, binning.cpp) ---- */
/* EWA projection of N 3D Gaussians (projection_math.h; docs/guides/rendering.md): means (N, 3), quats (N, 4)
 * (w, x, y, z, any norm), scales (N, 3) seen by a pinhole camera: viewmat (4, 4) world-to-camera row-major,
 * focal lengths and principal point in pixels, the image's width and height, near and far planes (camera z),
 * blur (pixels^2 added to the 2D covariance's diagonal), antialias (1: compensation = the opacity factor that
 * keeps the blurred Gaussian's integral, else 1). Writes means2d (N, 2) pixels, conics (N, 3) (the inverse 2D
 * covariance's a, b, c), radii int32 (N,) pixels (0: culled), depths (N,) camera z, compensation (N,). Each
 * Gaussian from its own inputs alone: the same bits for any thread count. */
MLX3D_API int mlx3d_project_ewa(const float* means, const float* quats, const float* scales, int64_t n, const float* viewmat,
                                float fx, float fy, float cx, float cy, int width, int height, float near_z, float far_z, float blur,
                                int antialias, int threads, float* means2d, float* conics, int32_t* radii, float* depths,
                                float* compensation);
/* Its vector-Jacobian product: from dL/dmeans2d (N, 2), dL/dconics (N, 3), dL/ddepths (N,), dL/dcompensation
 * (N,), the gradients d_means (N, 3), d_quats (N, 4), d_scales (N, 3). */
MLX3D_API int mlx3d_project_ewa_backward(const float* means, const float* quats, const float* scales, int64_t n,
                                         const float* viewmat, float fx, float fy, float cx, float cy, int width, int height,
                                         float near_z, float far_z, float blur, int antialias, const float* d_means2d,
                                         const float* d_conics, const float* d_depths, const float* d_compensation, int threads,
                                         float* d_means, float* d_quats, float* d_scales);
/* Tile binning (binning.cpp): the (Gaussian, tile) intersections of N Gaussians, means2d (N, 2) pixels, radii (N,)
 * pixels (<= 0: culled), depths (N,) camera z, in tiles of tile_size pixels over a width x height image; with
 * conics (N, 3) and opacities (N,) (both or neither NULL) each extent is tightened to the box where alpha can
 * reach 1/255. Writes tile_offsets int32 (tiles + 1,) and returns in *flatten_ids a new int32 array of the *m
 * entries, sorted by tile, then depth, then index (NULL when *m = 0; free it with mlx3d_free). The same for any
 * thread count. Fails when there are more than 2^31 entries. */
MLX3D_API int mlx3d_bin_tiles(const float* means2d, const float* radii, const float* depths, int64_t n, int width, int height,
                              int tile_size, const float* conics, const float* opacities, int threads, int32_t* tile_offsets,
                              int32_t** flatten_ids, int64_t* m);
/* The half-extents (N, 2) pixels that mlx3d_bin_tiles gives each Gaussian. */
MLX3D_API int mlx3d_tile_extents(const float* radii, const float* conics, const float* opacities, int64_t n, float* extents);
/* Frees an array the library returned (mlx3d_bin_tiles' flatten_ids); NULL is ignored. */
MLX3D_API void mlx3d_free(void* block);

/* ---- photometric loss (photometric.cpp) ---- */

/* The 3DGS training loss of a render x against a photo y, float32 (H, W, C) each (colour values, data range 1),
 * and its gradient with respect to x:
 *   loss = (1 - lambda) L1 + lambda (1 - SSIM),  L1 = sum_p w_p mean_c |x - y| / S,  SSIM = sum_p w_p mean_c s / S,
 * S = max(sum_p w_p, 1e-12), w = weights (H, W) or NULL (all 1); s the SSIM map of 3DGS: per channel, mu, E[x^2],
 * E[y^2], E[xy] from the zero-padded "same" filter with outer(taps, taps) (taps (ntaps,), ntaps odd, symmetric),
 * C1 = 0.01^2, C2 = 0.03^2. Writes loss (1,) and grad (H, W, C) = dloss/dx; the loss is symmetric, so dloss/dy is
 * the call with x and y swapped. lambda in [0, 1]; H, W, C >= 1 and H W C < 2^31 (also for mlx3d_mse). scratch:
 * 8 H W C floats of working memory (their contents of no value before or after), or NULL to have the call allocate
 * it. Per element in float32; the weights' sum, each row's weighted L1 and SSIM sums and their sums over rows (in
 * row order) in float64, so the results are the same for any thread count (mlx3d.training.metrics' photometric_loss,
 * float32 sums there). */
MLX3D_API int mlx3d_photometric_loss(const float* x, const float* y, const float* weights, int64_t h, int64_t w, int64_t c,
                                     float lambda, const float* taps, int64_t ntaps, int threads, float* scratch, float* loss,
                                     float* grad);
/* The mean squared error of x (clipped to [0, 1] first when clip != 0) against y, float32 (H, W, C) each:
 *   out (1,) = sum_p w_p mean_c (x - y)^2 / max(sum_p w_p, 1e-12),
 * w = weights (H, W) or NULL (all 1). Each pixel's channel sum in float32; the weighted sums per row, then over rows
 * in row order, in float64, so the result is the same for any thread count. A metric (the per-step PSNR): no
 * gradient. */
MLX3D_API int mlx3d_mse(const float* x, const float* y, const float* weights, int64_t h, int64_t w, int64_t c, int clip, int threads,
                        float* out);

/* ---- optimizer and activations (adam.cpp, activation.cpp, affine.cpp) ---- */

/* One Adam step on n float32 elements is three calls: mlx3d_adam_moment for m' (squared 0, beta = b1), again
 * for v' (squared 1, beta = b2), then mlx3d_adam_param for p'. In float32, the scalars rounded to float32 first
 * (1 - beta computed in double), as MLX rounds Python scalars that meet a float32 array:
 *   out = beta x + (1 - beta) g   (squared 0),   out = beta x + (1 - beta) g²   (squared 1);
 *   p_out = p - lr (m / c1) / (sqrt(v / c2) + eps),   c1 = 1 - b1^t, c2 = 1 - b2^t (> 0): the bias corrections.
 * All (n,). In place allowed: out may be x, and p_out may be p (the moment or parameter updated in place, as
 * mlx3d._core does where MLX donates the buffer); an output may not otherwise overlap an input. */
MLX3D_API int mlx3d_adam_moment(const float* g, const float* x, int64_t n, double beta, int squared, int threads, float* out);
MLX3D_API int mlx3d_adam_param(const float* p, const float* m, const float* v, int64_t n, double lr, double eps, double c1,
                               double c2, int threads, float* p_out);
/* *finite = 1 when no element of x (n,) is NaN or infinite (exponent bits all ones), else 0; 1 when n = 0. */
MLX3D_API int mlx3d_all_finite(const float* x, int64_t n, int threads, uint8_t* finite);
/* y = e^x and y = 1 / (1 + e^-x), elementwise over x (n,) float32, bit for bit MLX's CPU mx.exp / mx.sigmoid
 * (MLX's scalar algorithm: a range reduction to 2^i and a degree-6 polynomial with fma; x > 88: inf,
 * x < -88: 0, NaN stays NaN). The gradients are left to MLX (cot y and cot y (1 - y)). */
MLX3D_API int mlx3d_exp(const float* x, int64_t n, int threads, float* y);
MLX3D_API int mlx3d_sigmoid(const float* x, int64_t n, int threads, float* y);
/* Covariances Σ = R(q) diag(e^log_scales)² R(q)ᵀ of n Gaussians mapped by a linear map L (3, 3) float64,
 * row-major: L Σ Lᵀ re-decomposed (one-sided Jacobi SVD of L R diag(s), in double) into unit quaternions
 * quats_out (n, 4) (w, x, y, z; w >= 0) and log scales log_scales_out (n, 3), sorted descending (natural log
 * of the scale; a vanished scale gives log of DBL_MIN). quats (n, 4) need not be unit; log_scales (n, 3). */
MLX3D_API int mlx3d_affine_covariances(const double* linear, const float* quats, const float* log_scales, int64_t n, int threads,
                                       float* quats_out, float* log_scales_out);

#ifdef __cplusplus
}
#endif

#endif /* MLX3D_KERNELS_H */
