/* Test driver of the kernel library: runs the calls a file describes and writes what they returned.
 *
 *     kernel_driver LIBRARY CALLS OUT
 *
 * Loads LIBRARY as a program would (LoadLibrary / dlopen; the library's own exports only), so the same
 * calls can be run by each platform's build where it runs: natively, under wine or under qemu-user
 * (tests/test_kernel_platforms.py writes CALLS and compares the OUT files).
 *
 * CALLS: "MLX3DK1\n", then records until the end of the file, each: u32 name length, the function's name,
 * u32 argument count, then per argument one kind byte and a u64: 'i' an integer argument (the u64, as
 * two's complement), 'x' a double argument (the u64's bits), or the element count of an array whose elements
 * follow for inputs: 'f' float32, 'u' uint8, 'n' int32, 'D' float64 updated in place; 'o' a float32 and 'l'
 * an int64 output array (nothing follows). OUT: per record, i32 the return value, u32 length and text of
 * mlx3d_last_error(), then per 'o', 'l' and 'D' argument u64 count and its elements. Little-endian throughout.
 * Also: 'd' a float64 input, 'F' a float32 array updated in place (elements follow; in OUT as 'D'), 'b' a uint8
 * output array (nothing follows; in OUT as 'o'). A record of mlx3d_adam_moment or mlx3d_adam_param with its
 * updated array (x, p) as 'F' and no output argument calls it in place (output = that array).
 * The record "mlx3d_knn" builds a tree, queries it and frees it (the API's three calls), with the arguments
 * points, n, leaf size, queries, m, k, output, threads, out_dist, out_index.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if defined(_WIN32)
#include <windows.h>
typedef HMODULE library_t;
static library_t open_library(const char* path) { return LoadLibraryA(path); }
static void* symbol(library_t lib, const char* name) { return (void*)GetProcAddress(lib, name); }
#else
#include <dlfcn.h>
typedef void* library_t;
static library_t open_library(const char* path) { return dlopen(path, RTLD_NOW | RTLD_LOCAL); }
static void* symbol(library_t lib, const char* name) { return dlsym(lib, name); }
#endif

#define MAX_ARGS 32

static void fail(const char* what) {
  fprintf(stderr, "kernel_driver: %s\n", what);
  exit(2);
}

typedef struct {
  char kind;
  uint64_t count;
  void* data;
} Arg;

/* Bytes per element of an array argument's kind; 0 for a scalar. */
static size_t element_size(char kind) {
  switch (kind) {
    case 'f': case 'o': case 'n': case 'F': return 4;
    case 'u': case 'b': return 1;
    case 'D': case 'l': case 'd': return 8;
    case 'i': case 'x': return 0;
    default: fail("unknown argument kind");
  }
  return 0;
}

static void read_exact(FILE* f, void* p, size_t n) {
  if (n && fread(p, 1, n, f) != n) fail("truncated calls file");
}

static void write_exact(FILE* f, const void* p, size_t n) {
  if (n && fwrite(p, 1, n, f) != n) fail("cannot write the output file");
}

typedef int (*sh_forward_t)(const float*, int64_t, const float*, int64_t, const float*, const float*, int64_t, int, int, float*);
typedef int (*sh_backward_t)(const float*, int64_t, const float*, int64_t, const float*, const float*, int64_t, int, const float*, int,
                             float*, float*, float*);
typedef int (*knn_build_t)(const float*, int64_t, int, void**);
typedef int (*knn_free_t)(void*);
typedef int (*knn_query_t)(const void*, const float*, int64_t, int, const int64_t*, int, int, int64_t*, float*);
typedef int (*statistics_t)(const uint8_t*, const float*, const int32_t*, int64_t, double, double, double*, double*, double*, int);

typedef int (*raster_forward_t)(const float*, const float*, const float*, const float*, const int32_t*, const int32_t*, int64_t,
                                int, int64_t, int, int, int, const float*, int, float*, float*, int32_t*, float*);
typedef int (*raster_backward_t)(const float*, const float*, const float*, const float*, const int32_t*, const int32_t*, int64_t,
                                 int, int64_t, int, int, int, const int32_t*, const float*, const float*, const float*,
                                 const float*, int, float*, float*, float*, float*);

typedef int (*project_t)(const float*, const float*, const float*, int64_t, const float*, float, float, float, float, int, int,
                         float, float, float, int, int, float*, float*, int32_t*, float*, float*);
typedef int (*project_backward_t)(const float*, const float*, const float*, int64_t, const float*, float, float, float, float, int,
                                  int, float, float, float, int, const float*, const float*, const float*, const float*, int, float*,
                                  float*, float*);

typedef int (*bin_tiles_t)(const float*, const float*, const float*, int64_t, int, int, int, const float*, const float*, int, int32_t*,
                           int32_t**, int64_t*);
typedef void (*free_t)(void*);

#define I(k) ((int64_t)args[k].count)
#define N(k) ((const int32_t*)args[k].data)
#define F(k) ((float*)args[k].data)
#define X(k) (as_double(args[k].count))

static double as_double(uint64_t bits) {
  double d;
  memcpy(&d, &bits, sizeof d);
  return d;
}

/* Whether the arguments' kinds spell `want` ("fio...", one letter per argument). */
static int kinds_are(const Arg* args, uint32_t nargs, const char* want) {
  if (strlen(want) != nargs) return 0;
  for (uint32_t k = 0; k < nargs; ++k)
    if (args[k].kind != want[k]) return 0;
  return 1;
}

/* Calls `name` with `args` (their kinds checked against its signature); the function's return value. */
static int call(library_t lib, const char* name, Arg* args, uint32_t nargs) {
  if (!strcmp(name, "mlx3d_knn")) {
    if (!kinds_are(args, nargs, "fiifiiiiol")) fail("mlx3d_knn: arguments of the wrong kinds");
    knn_build_t build = (knn_build_t)symbol(lib, "mlx3d_knn_build");
    knn_query_t query = (knn_query_t)symbol(lib, "mlx3d_knn_query");
    knn_free_t release = (knn_free_t)symbol(lib, "mlx3d_knn_free");
    if (!build || !query || !release) fail("the library has no k-NN functions");
    void* tree = NULL;
    int rc = build(F(0), I(1), (int)I(2), &tree);
    if (rc == 0) rc = query(tree, F(3), I(4), (int)I(5), NULL, (int)I(6), (int)I(7), (int64_t*)args[9].data, F(8));
    if (tree && release(tree) != 0) fail("mlx3d_knn_free failed");
    return rc;
  }
  void* fn = symbol(lib, name);
  if (!fn) fail("the library has no function of that name");
  if (!strcmp(name, "mlx3d_sh_forward")) {
    if (!kinds_are(args, nargs, "fififfiiio")) fail("mlx3d_sh_forward: arguments of the wrong kinds");
    return ((sh_forward_t)fn)(F(0), I(1), F(2), I(3), F(4), F(5), I(6), (int)I(7), (int)I(8), F(9));
  }
  if (!strcmp(name, "mlx3d_sh_backward")) {
    if (!kinds_are(args, nargs, "fififfiifiooo")) fail("mlx3d_sh_backward: arguments of the wrong kinds");
    return ((sh_backward_t)fn)(F(0), I(1), F(2), I(3), F(4), F(5), I(6), (int)I(7), F(8), (int)I(9), F(10), F(11), F(12));
  }
  if (!strcmp(name, "mlx3d_add_screen_statistics")) {
    if (!kinds_are(args, nargs, "ufnixxDDDi")) fail("mlx3d_add_screen_statistics: arguments of the wrong kinds");
    return ((statistics_t)fn)((const uint8_t*)args[0].data, F(1), (const int32_t*)args[2].data, I(3), X(4), X(5), (double*)args[6].data,
                              (double*)args[7].data, (double*)args[8].data, (int)I(9));
  }
  /* ---- rasterizer ---- */
  if (!strcmp(name, "mlx3d_rasterizer_lanes")) {  /* no arguments; its value as the record's return value */
    if (nargs != 0) fail("mlx3d_rasterizer_lanes: takes no arguments");
    return ((int (*)(void))fn)();
  }
  if (!strcmp(name, "mlx3d_rasterize_forward")) {  /* 'o' for last: an int32 output, compared as bytes */
    if (!kinds_are(args, nargs, "ffffnniiiiiifioooo")) fail("mlx3d_rasterize_forward: arguments of the wrong kinds");
    return ((raster_forward_t)fn)(F(0), F(1), F(2), F(3), N(4), N(5), I(6), (int)I(7), I(8), (int)I(9), (int)I(10), (int)I(11),
                                  F(12), (int)I(13), F(14), F(15), (int32_t*)args[16].data, F(17));
  }
  if (!strcmp(name, "mlx3d_rasterize_backward")) {
    if (!kinds_are(args, nargs, "ffffnniiiiiinffffioooo")) fail("mlx3d_rasterize_backward: arguments of the wrong kinds");
    return ((raster_backward_t)fn)(F(0), F(1), F(2), F(3), N(4), N(5), I(6), (int)I(7), I(8), (int)I(9), (int)I(10), (int)I(11),
                                   N(12), F(13), F(14), F(15), F(16), (int)I(17), F(18), F(19), F(20), F(21));
  }
  /* ---- projection and tile binning ---- */
  if (!strcmp(name, "mlx3d_bin_tiles")) {  /* the entries, which the library allocates, copied into the last 'o' (its count) */
    if (!kinds_are(args, nargs, "fffiiiiffioo")) fail("mlx3d_bin_tiles: arguments of the wrong kinds");
    int32_t* ids = NULL;
    int64_t m = 0;
    const int rc = ((bin_tiles_t)fn)(F(0), F(1), F(2), I(3), (int)I(4), (int)I(5), (int)I(6), F(7), F(8), (int)I(9),
                                     (int32_t*)args[10].data, &ids, &m);
    if (rc == 0 && (uint64_t)m != args[11].count) fail("mlx3d_bin_tiles: another count of entries than the calls file expects");
    if (m) memcpy(args[11].data, ids, (size_t)m * 4);
    ((free_t)symbol(lib, "mlx3d_free"))(ids);
    return rc;
  }
  if (!strcmp(name, "mlx3d_project_ewa")) {  /* 'x' for the float scalars; 'o' for radii: an int32 output, compared as bytes */
    if (!kinds_are(args, nargs, "fffifxxxxiixxxiiooooo")) fail("mlx3d_project_ewa: arguments of the wrong kinds");
    return ((project_t)fn)(F(0), F(1), F(2), I(3), F(4), (float)X(5), (float)X(6), (float)X(7), (float)X(8), (int)I(9), (int)I(10),
                           (float)X(11), (float)X(12), (float)X(13), (int)I(14), (int)I(15), F(16), F(17), (int32_t*)args[18].data,
                           F(19), F(20));
  }
  if (!strcmp(name, "mlx3d_project_ewa_backward")) {
    if (!kinds_are(args, nargs, "fffifxxxxiixxxiffffiooo")) fail("mlx3d_project_ewa_backward: arguments of the wrong kinds");
    return ((project_backward_t)fn)(F(0), F(1), F(2), I(3), F(4), (float)X(5), (float)X(6), (float)X(7), (float)X(8), (int)I(9),
                                    (int)I(10), (float)X(11), (float)X(12), (float)X(13), (int)I(14), F(15), F(16), F(17), F(18),
                                    (int)I(19), F(20), F(21), F(22));
  }
  /* ---- photometric loss ---- */
  if (!strcmp(name, "mlx3d_photometric_loss")) {  /* weights and scratch: NULL when of count 0; lambda: the double as a float */
    typedef int (*photometric_loss_t)(const float*, const float*, const float*, int64_t, int64_t, int64_t, float, const float*, int64_t,
                                      int, float*, float*, float*);
    if (!kinds_are(args, nargs, "fffiiixfiiooo")) fail("mlx3d_photometric_loss: arguments of the wrong kinds");
    return ((photometric_loss_t)fn)(F(0), F(1), F(2), I(3), I(4), I(5), (float)X(6), F(7), I(8), (int)I(9), F(10), F(11), F(12));
  }
  if (!strcmp(name, "mlx3d_mse")) {  /* weights: NULL when of count 0 */
    if (!kinds_are(args, nargs, "fffiiiiio")) fail("mlx3d_mse: arguments of the wrong kinds");
    return ((int (*)(const float*, const float*, const float*, int64_t, int64_t, int64_t, int, int, float*))fn)(
        F(0), F(1), F(2), I(3), I(4), I(5), (int)I(6), (int)I(7), F(8));
  }
  /* ---- optimizer and activations ---- */
  if (!strcmp(name, "mlx3d_adam_moment")) {
    typedef int (*adam_moment_t)(const float*, const float*, int64_t, double, int, int, float*);
    if (kinds_are(args, nargs, "ffixiio")) return ((adam_moment_t)fn)(F(0), F(1), I(2), X(3), (int)I(4), (int)I(5), F(6));
    if (kinds_are(args, nargs, "fFixii")) return ((adam_moment_t)fn)(F(0), F(1), I(2), X(3), (int)I(4), (int)I(5), F(1));
    fail("mlx3d_adam_moment: arguments of the wrong kinds");
  }
  if (!strcmp(name, "mlx3d_adam_param")) {
    typedef int (*adam_param_t)(const float*, const float*, const float*, int64_t, double, double, double, double, int, float*);
    if (kinds_are(args, nargs, "fffixxxxio")) return ((adam_param_t)fn)(F(0), F(1), F(2), I(3), X(4), X(5), X(6), X(7), (int)I(8), F(9));
    if (kinds_are(args, nargs, "Fffixxxxi")) return ((adam_param_t)fn)(F(0), F(1), F(2), I(3), X(4), X(5), X(6), X(7), (int)I(8), F(0));
    fail("mlx3d_adam_param: arguments of the wrong kinds");
  }
  if (!strcmp(name, "mlx3d_all_finite")) {
    if (!kinds_are(args, nargs, "fiib")) fail("mlx3d_all_finite: arguments of the wrong kinds");
    return ((int (*)(const float*, int64_t, int, uint8_t*))fn)(F(0), I(1), (int)I(2), (uint8_t*)args[3].data);
  }
  if (!strcmp(name, "mlx3d_exp") || !strcmp(name, "mlx3d_sigmoid")) {
    if (!kinds_are(args, nargs, "fiio")) fail("mlx3d_exp / mlx3d_sigmoid: arguments of the wrong kinds");
    return ((int (*)(const float*, int64_t, int, float*))fn)(F(0), I(1), (int)I(2), F(3));
  }
  if (!strcmp(name, "mlx3d_affine_covariances")) {
    if (!kinds_are(args, nargs, "dffiioo")) fail("mlx3d_affine_covariances: arguments of the wrong kinds");
    return ((int (*)(const double*, const float*, const float*, int64_t, int, float*, float*))fn)((const double*)args[0].data, F(1), F(2),
                                                                                                  I(3), (int)I(4), F(5), F(6));
  }
  fail("no call of that function is known to the driver");
  return -1;
}

int main(int argc, char** argv) {
  if (argc != 4) fail("usage: kernel_driver LIBRARY CALLS OUT");
  library_t lib = open_library(argv[1]);
  if (!lib) fail("cannot load the library");
  const char* (*last_error)(void) = (const char* (*)(void))symbol(lib, "mlx3d_last_error");
  if (!last_error) fail("the library has no mlx3d_last_error");
  FILE* in = fopen(argv[2], "rb");
  FILE* out = fopen(argv[3], "wb");
  if (!in || !out) fail("cannot open the calls or the output file");
  char magic[8];
  read_exact(in, magic, 8);
  if (memcmp(magic, "MLX3DK1\n", 8)) fail("not a calls file");
  uint32_t length;
  while (fread(&length, 4, 1, in) == 1) {
    char name[256];
    if (length >= sizeof name) fail("function name too long");
    read_exact(in, name, length);
    name[length] = 0;
    uint32_t nargs;
    read_exact(in, &nargs, 4);
    if (nargs > MAX_ARGS) fail("too many arguments");
    Arg args[MAX_ARGS];
    for (uint32_t k = 0; k < nargs; ++k) {
      read_exact(in, &args[k].kind, 1);
      read_exact(in, &args[k].count, 8);
      args[k].data = NULL;
      const size_t size = element_size(args[k].kind);
      if (size && args[k].count) {
        args[k].data = malloc(args[k].count * size);
        if (!args[k].data) fail("out of memory");
        if (args[k].kind == 'o' || args[k].kind == 'l' || args[k].kind == 'b') memset(args[k].data, 0xff, args[k].count * size);  /* NaN / -1: unwritten shows */
        else read_exact(in, args[k].data, args[k].count * size);
      }
    }
    const int32_t rc = call(lib, name, args, nargs);
    const char* error = last_error();
    const uint32_t error_length = (uint32_t)strlen(error);
    write_exact(out, &rc, 4);
    write_exact(out, &error_length, 4);
    write_exact(out, error, error_length);
    for (uint32_t k = 0; k < nargs; ++k) {
      if (args[k].kind == 'o' || args[k].kind == 'l' || args[k].kind == 'D' || args[k].kind == 'F' || args[k].kind == 'b') {
        write_exact(out, &args[k].count, 8);
        write_exact(out, args[k].data, args[k].count * element_size(args[k].kind));
      }
      free(args[k].data);
    }
  }
  fclose(in);
  if (fclose(out)) fail("cannot write the output file");
  return 0;
}
