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
    case 'f': case 'o': case 'n': return 4;
    case 'u': return 1;
    case 'D': case 'l': return 8;
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

#define I(k) ((int64_t)args[k].count)
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
  /* ---- projection and tile binning ---- */
  /* ---- photometric loss ---- */
  /* ---- optimizer and activations ---- */
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
        if (args[k].kind == 'o' || args[k].kind == 'l') memset(args[k].data, 0xff, args[k].count * size);  /* NaN / -1: unwritten shows */
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
      if (args[k].kind == 'o' || args[k].kind == 'l' || args[k].kind == 'D') {
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
