# The README's two commands: `make demo` runs the main job end to end in Blender
# on the built-in default scene; `make test` runs the test suite on each supported
# Blender/Python/numpy combination (the matrix below). Both create their virtual
# environments and build the compiled extension on first use.

# Interpreters. `find_python` prints the newest pyenv install of Python X.Y
# (`pyenv root`/versions/X.Y.*), else pythonX.Y on PATH, keeping only one that
# runs and reports X.Y (a pyenv shim of a version that is not selected fails);
# it prints nothing when there is none. Pass PYTHON311=... or PYTHON313=... to
# use another interpreter.
find_python = $(shell for p in $$(ls -d "$$(pyenv root 2>/dev/null)"/versions/$(1).*/bin/python$(1) 2>/dev/null | sort -rV) python$(1); do \
	v=$$("$$p" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null) && [ "$$v" = "$(1)" ] && { command -v "$$p"; break; }; done)
PYTHON311 ?= $(call find_python,3.11)
PYTHON313 ?= $(call find_python,3.13)

# The venv the other targets use (`make demo`, `make bench`, ...) and the exact
# bpy (Blender as a Python module, for tests/blender) and numpy installed into it
# with the package and its [test] extra. Without BPY=/NUMPY=, the pins follow the
# venv's Python: bpy 5.0.1 with numpy 1.26.4 (as Blender 4.5 and 5.0 ship) for
# 3.11, bpy 5.2.3 with numpy 2.5.5 (Blender 5.1+ ship numpy 2) for 3.13.
PYTHON ?= $(PYTHON311)
VENV ?= .venv
PY := $(VENV)/bin/python
PY_VERSION := $(shell $(if $(wildcard $(PY)),$(PY),$(or $(PYTHON),false)) -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)
BPY_3.11 := 5.0.1
BPY_3.13 := 5.2.3
NUMPY_3.11 := 1.26.4
NUMPY_3.13 := 2.5.5
BPY ?= $(BPY_$(PY_VERSION))
NUMPY ?= $(NUMPY_$(PY_VERSION))
# The stamp names the pins, so a venv is reinstalled when one changes.
STAMP := $(VENV)/.mlx3d-installed-bpy$(BPY)-numpy$(NUMPY)
# CMake build directory of the editable install. Venvs of the same Python would
# otherwise share build/{wheel_tag}, and an editable _core links to the MLX of
# the venv that configured it, so every venv but .venv builds under its own name.
BUILD_DIR ?= build/$(if $(filter .venv,$(VENV)),,$(VENV:.%=%)/){wheel_tag}

# `make test` runs every entry, in its own venv, and fails if any failed:
#   test-py311      .venv            Python 3.11, bpy 5.0.1 (numpy 1.26, as Blender 4.5 and 5.0): whole suite
#   test-py313      .venv-py313      Python 3.13, bpy 5.2.3 (numpy 2.x, as Blender 5.1+): whole suite but the long
#                    trainings and the packaging tests (tests/core_marks.py: MLX3D_SECOND_SUITE), which test-py311 runs
#   test-blender45  .venv-blender45  Python 3.11, bpy 4.5.x LTS: tests/blender (the installed extension zip)
#   test-blender53  .venv-blender53  Python 3.13, bpy 5.3.0 (numpy 2.x): tests/blender, incl. Blender's own 3DGS import
#   test-pip-editable  (temporary)   Python 3.11: a contributor's plain `pip install -e .` (build isolation)
#                    imports the compiled module and runs `python -m mlx3d`
#   test-pure       .venv            Python 3.11: the suite with the compiled kernels turned off (MLX3D_NO_CORE=1),
#                    as where neither _core nor the kernel library loads; the tests of the kernels themselves, of
#                    what runs no kernel and of what is built above the kernels (command line, docs, report, the
#                    add-on's training, photo, mesh, benchmark and demo operators) skip
#   test-mac-path   .venv            Python 3.11: the Apple-GPU path (Metal backend forced, the Metal kernels'
#                    sources compiled as C++, _core off): tests/test_mac_path.py, tests/test_rasterize_metal.py
#   test-clang      .venv-clang      Python 3.11: the compiled module built with clang (clang++ on PATH),
#                    as Apple clang builds it on macOS, and the kernel tests against it
#   test-macos-compile .venv-macos   the module's C++ sources cross-compiled for macOS arm64 (zig c++,
#                    the macOS MLX wheel's headers): tests/test_macos_compile.py
#   test-kernel-platforms .venv      the kernel library (mlx3d/csrc/kernels) built for linux-x64, windows-x64,
#                    linux-arm64 and macos-arm64 (zig), the Windows DLL run under wine and the arm64 library under
#                    qemu-user against the Linux build, the macOS one inspected: tests/test_kernel_platforms.py
#   test-library    .venv            the kernels' tests with the kernel library through ctypes in place of
#                    mlx3d._core (MLX3D_CPU_KERNELS=library), as Windows, Linux arm64 and macOS' CPU path run
#                    them: LIBRARY_TESTS
#   test-docs       .venv            the documentation site built strictly (`make docs`); the pages'
#                    examples run in the suites above (tests/test_docs.py)
# Each entry prints its wall time. PYTEST_ARGS adds pytest options (e.g. -x, -k).
TEST_MATRIX := test-py311 test-py313 test-blender45 test-blender53 test-pip-editable test-pure test-mac-path test-clang test-macos-compile \
	test-kernel-platforms test-library test-docs
BPY_LTS := 4.5.15
BPY_LATEST := 5.3.0
PYTEST_ARGS ?=

.PHONY: demo test $(TEST_MATRIX) test-venv peer-tools zig cross-tools kernels bench bench-scenes report install extension docs

# `make demo` runs the Blender extension as a user would: it builds the extension
# zip for this machine and the venv's Python (build/demo-extension/), installs and
# enables it in a project-local Blender user folder (.blender-user/, git-ignored,
# made afresh each time) and runs the installed add-on's headless `demo` command:
# scene -> capture -> training -> held-out PSNR/SSIM -> PLY export and re-import
# (files in demo_out/; see addon/demo.py).
BLENDER_USER := $(CURDIR)/.blender-user
DEMO_ZIP_DIR := build/demo-extension
EXTENSION_ID := mlx3d_splat
# The operator reports FINISHED even when it installs nothing: check the result.
INSTALL_EXTENSION := import sys, pathlib, bpy; \
	zip_path = sys.argv[1]; \
	bpy.ops.extensions.package_install_files(filepath=zip_path, repo='user_default', enable_on_install=True); \
	target = pathlib.Path(bpy.utils.user_resource('EXTENSIONS')) / 'user_default' / '$(EXTENSION_ID)'; \
	enabled = 'bl_ext.user_default.$(EXTENSION_ID)' in bpy.context.preferences.addons; \
	ok = enabled and (target / 'blender_manifest.toml').is_file(); \
	ok and bpy.ops.wm.save_userpref(); \
	ok and print(f'installed and enabled {pathlib.Path(zip_path).name} in {target}'); \
	sys.exit(0 if ok else f'could not install and enable {zip_path} in {target}')

demo: $(STAMP)
	rm -rf $(DEMO_ZIP_DIR) $(BLENDER_USER)
	$(PY) addon/package.py --python "$$($(PY) -c 'import sys; print("%d.%d" % sys.version_info[:2])')" --out $(DEMO_ZIP_DIR)
	BLENDER_USER_RESOURCES=$(BLENDER_USER) $(PY) -c "$(INSTALL_EXTENSION)" $(DEMO_ZIP_DIR)/$(EXTENSION_ID)-*.zip
	BLENDER_USER_RESOURCES=$(BLENDER_USER) $(PY) $(BLENDER_USER)/extensions/user_default/$(EXTENSION_ID)/addon/blender_splat.py demo --out demo_out

test:
	@failed=; for entry in $(TEST_MATRIX); do \
		start=$$(date +%s); \
		$(MAKE) --no-print-directory $$entry || failed="$$failed $$entry"; \
		echo "make $$entry: $$(( $$(date +%s) - start )) s"; \
	done; \
	if [ -n "$$failed" ]; then echo "make test: failed:$$failed" >&2; exit 1; fi

test-py311:
	@$(call require_python,3.11,$(PYTHON311))
	$(MAKE) --no-print-directory zig VENV=.venv PYTHON="$(PYTHON311)" BPY=$(BPY_3.11)
	$(MAKE) --no-print-directory test-venv VENV=.venv PYTHON="$(PYTHON311)" BPY=$(BPY_3.11)

test-py313:
	@$(call require_python,3.13,$(PYTHON313))
	MLX3D_SECOND_SUITE=1 $(MAKE) --no-print-directory test-venv VENV=.venv-py313 PYTHON="$(PYTHON313)" BPY=$(BPY_3.13)

test-blender45:
	@$(call require_python,3.11,$(PYTHON311))
	$(MAKE) --no-print-directory test-venv VENV=.venv-blender45 PYTHON="$(PYTHON311)" BPY=$(BPY_LTS) TESTS=tests/blender

test-blender53:
	@$(call require_python,3.13,$(PYTHON313))
	$(MAKE) --no-print-directory test-venv VENV=.venv-blender53 PYTHON="$(PYTHON313)" BPY=$(BPY_LATEST) TESTS=tests/blender

test-pip-editable:
	@$(call require_python,3.11,$(PYTHON311))
	@tmp=$$(mktemp -d) && trap 'rm -rf "$$tmp"' EXIT && \
	"$(PYTHON311)" -m venv "$$tmp/venv" && \
	"$$tmp/venv/bin/python" -m pip install -q -e . && \
	cd "$$tmp" && "$$tmp/venv/bin/python" -c "import mlx3d._core, mlx3d; print('pip install -e .: mlx3d._core from', mlx3d._core.__file__)" && \
	"$$tmp/venv/bin/python" -m mlx3d --help > /dev/null && echo "pip install -e .: python -m mlx3d runs"

test-pure: $(STAMP)
	MLX3D_NO_CORE=1 $(PY) -m pytest -q $(PYTEST_ARGS)

test-mac-path: $(STAMP)
	MLX3D_NO_CORE=1 $(PY) -m pytest -q $(PYTEST_ARGS) tests/test_mac_path.py tests/test_rasterize_metal.py

# Every kernel, forward and backward, and a training step through the library (the kernels' own modules,
# the trainer's, the frozen runs and the densification statistics).
LIBRARY_TESTS := tests/test_rasterize_cpu.py tests/test_projection_kernel.py tests/test_render_binning.py tests/test_sh_color.py \
	tests/test_photometric_kernel.py tests/test_activation.py tests/test_transforms.py tests/test_neighbors.py \
	tests/test_surface_composite.py tests/test_trainer.py tests/test_train_batches.py
test-library: $(STAMP) kernels
	MLX3D_CPU_KERNELS=library $(PY) -c "from mlx3d import native; print('CPU kernels from', native.core().__name__)"
	MLX3D_CPU_KERNELS=library $(PY) -m pytest -q $(PYTEST_ARGS) $(LIBRARY_TESTS)

# The compiled module built with clang (CLANGXX=... for another clang++) in its own venv and build
# directory (no bpy: the kernel tests do not need Blender). Clang takes the kernels' vector lanes as
# GCC does, but not GCC's target_clones variants nor its scheduling flags; the frozen and bitwise
# tests hold it to the GCC build's results.
CLANGXX ?= clang++
CLANG_VENV := .venv-clang
CLANG_STAMP := $(CLANG_VENV)/.mlx3d-clang-installed-numpy$(NUMPY_3.11)
CLANG_TESTS := tests/test_rasterize_cpu.py tests/test_rasterize_metal.py tests/test_projection_kernel.py \
	tests/test_sh_color.py tests/test_photometric_kernel.py tests/test_activation.py tests/test_neighbors.py \
	tests/test_render_binning.py tests/test_transforms.py tests/test_trainer.py
test-clang: $(CLANG_STAMP)
	$(CLANG_VENV)/bin/python -m pytest -q $(PYTEST_ARGS) $(CLANG_TESTS)

$(CLANG_STAMP): pyproject.toml CMakeLists.txt
	@$(call require_python,3.11,$(PYTHON311))
	@command -v $(CLANGXX) > /dev/null || [ "$(CLANGXX)" != clang++ ] || ! command -v apt-get > /dev/null || [ "$$(id -u)" != 0 ] || \
		{ echo "make: installing clang (apt-get install clang)"; apt-get update -q > /dev/null && apt-get install -y -q clang > /dev/null; }
	@command -v $(CLANGXX) > /dev/null || { echo "make: $(CLANGXX) was not found: install clang (Debian/Ubuntu: apt-get install clang) or pass CLANGXX=/path/to/clang++" >&2; exit 1; }
	test -x $(CLANG_VENV)/bin/python || "$(PYTHON311)" -m venv $(CLANG_VENV)
	$(CLANG_VENV)/bin/python -c "import subprocess, sys, tomllib; reqs = tomllib.load(open('pyproject.toml', 'rb'))['build-system']['requires']; subprocess.check_call([sys.executable, '-m', 'pip', 'install', '-q', *reqs])"
	$(CLANG_VENV)/bin/python -m pip install -q --no-build-isolation -C build-dir=build/venv-clang/{wheel_tag} -C editable.rebuild=true \
		-C cmake.define.CMAKE_CXX_COMPILER="$$(command -v $(CLANGXX))" -e ".[test]" "numpy==$(NUMPY_3.11)"
	rm -f $(CLANG_VENV)/.mlx3d-clang-installed*
	touch $@

# The macOS compile check: zig (PyPI's ziglang) and the macOS arm64 wheel of the pinned MLX's
# headers (mlx-metal, unpacked into build/macos-mlx/<version>/), nanobind's and Python's headers.
ZIGLANG ?= 0.17.1
MACOS_VENV := .venv-macos
MLX_PIN := $(shell sed -n 's/^ *"mlx==\([0-9.]*\);.*darwin.*/\1/p' pyproject.toml | head -n 1)
MACOS_MLX := build/macos-mlx/$(MLX_PIN)
test-macos-compile:
	@$(call require_python,3.11,$(PYTHON311))
	test -x $(MACOS_VENV)/bin/python || "$(PYTHON311)" -m venv $(MACOS_VENV)
	$(MACOS_VENV)/bin/python -c "import subprocess, sys, tomllib; reqs = tomllib.load(open('pyproject.toml', 'rb'))['build-system']['requires']; subprocess.check_call([sys.executable, '-m', 'pip', 'install', '-q', 'pytest', 'ziglang==$(ZIGLANG)', *[r for r in reqs if r.startswith('nanobind')]])"
	test -f $(MACOS_MLX)/mlx/include/mlx/mlx.h || { \
		$(MACOS_VENV)/bin/python -m pip download -q --no-deps --only-binary=:all: --platform macosx_14_0_arm64 -d $(MACOS_MLX) "mlx-metal==$(MLX_PIN)" && \
		$(MACOS_VENV)/bin/python -c "import glob, sys, zipfile; z = zipfile.ZipFile(glob.glob(sys.argv[1] + '/mlx_metal-*.whl')[0]); z.extractall(sys.argv[1], [n for n in z.namelist() if n.startswith('mlx/include/')])" $(MACOS_MLX) && \
		rm -f $(MACOS_MLX)/mlx_metal-*.whl; }
	MLX3D_MACOS_MLX_INCLUDE=$(MACOS_MLX)/mlx/include $(MACOS_VENV)/bin/python -m pytest -q $(PYTEST_ARGS) tests/test_macos_compile.py

# The kernel library for every platform (mlx3d/csrc/kernels/build.py) and where each runs here: zig
# (ziglang, pinned above) in .venv, and, as root on Debian/Ubuntu, wine (64-bit), qemu-user and the arm64 C
# library from apt; without them those tests skip with the reason.
CROSS_PACKAGES := wine64 qemu-user-static libc6-arm64-cross
test-kernel-platforms: $(STAMP) cross-tools
	MLX3D_KERNEL_PLATFORMS=1 $(PY) -m pytest -q $(PYTEST_ARGS) tests/test_kernel_platforms.py

# zig (PyPI's ziglang, pinned), which builds the kernel library for the other platforms: the extension zips
# (test-py311's packaging tests) and the platform tests need it.
zig: $(STAMP)
	@$(PY) -c "import importlib.metadata as m, sys; sys.exit(m.version('ziglang') != '$(ZIGLANG)')" 2>/dev/null || \
		$(PY) -m pip install -q ziglang==$(ZIGLANG)

cross-tools: zig
	@missing=$$(for p in $(CROSS_PACKAGES); do dpkg -s $$p > /dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ] && command -v apt-get > /dev/null && [ "$$(id -u)" = 0 ]; then \
		echo "make: installing $$missing (apt-get)"; \
		apt-get update -q > /dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $$missing > /dev/null; \
	elif [ -n "$$missing" ]; then echo "make: $$missing not installed; the kernel tests that need them will skip" >&2; fi

# The kernel library for this machine (Linux x86-64) where mlx3d.kernel_library finds it: mlx3d/_kernels/.
kernels: $(STAMP)
	$(PY) mlx3d/csrc/kernels/build.py linux-x64 --out mlx3d/_kernels

# The tests of one venv (VENV, PYTHON, BPY as above; TESTS: pytest paths).
TESTS ?=
test-venv: $(STAMP) peer-tools
	$(PY) -m pytest -q $(PYTEST_ARGS) $(TESTS)

# The peer tools the file-format tests compare with (tests/peer.py):
# @playcanvas/splat-transform and the Khronos glTF validator from the npm
# registry, in .tools/ (git-ignored). Without npm (or offline) those tests skip
# with the reason; the rest still run.
SPLAT_TRANSFORM_VERSION := 3.7.0
SPLAT_TRANSFORM := .tools/node_modules/.bin/splat-transform
GLTF_VALIDATOR_VERSION := 2.0.0-dev.3.10
peer-tools:
	@if [ -x $(SPLAT_TRANSFORM) ] && grep -q '"version": "$(SPLAT_TRANSFORM_VERSION)"' .tools/node_modules/@playcanvas/splat-transform/package.json 2>/dev/null; then :; \
	elif command -v npm >/dev/null 2>&1; then \
		mkdir -p .tools && npm install --prefix .tools --no-audit --no-fund --loglevel=error @playcanvas/splat-transform@$(SPLAT_TRANSFORM_VERSION) \
		|| echo "make: could not install @playcanvas/splat-transform@$(SPLAT_TRANSFORM_VERSION); the peer tests will skip" >&2; \
	else echo "make: npm not found; the file-format peer tests (splat-transform) will skip" >&2; fi
	@if grep -q '"version": "$(GLTF_VALIDATOR_VERSION)"' .tools/node_modules/gltf-validator/package.json 2>/dev/null; then :; \
	elif command -v npm >/dev/null 2>&1; then \
		mkdir -p .tools && npm install --prefix .tools --no-audit --no-fund --loglevel=error gltf-validator@$(GLTF_VALIDATOR_VERSION) \
		|| echo "make: could not install gltf-validator@$(GLTF_VALIDATOR_VERSION); its test will skip" >&2; fi

require_python = test -n "$(2)" || { echo "make: Python $(1) was not found (looked for pyenv's $(1).* and python$(1) on PATH): install it (e.g. 'pyenv install $(1)') or pass PYTHON$(subst .,,$(1))=/path/to/python$(1)" >&2; exit 1; }

bench: $(STAMP)
	$(PY) bench/ply_io.py
	$(PY) bench/knn.py
	$(PY) bench/from_points.py
	$(PY) bench/blender_io.py

# `make bench-scenes` renders the benchmark scene set into bench_data/scenes
# (git-ignored; a few minutes on 2 cores) for `bench/train.py --suite bench_data/scenes`.
bench-scenes: $(STAMP)
	$(PY) bench/scenes.py

# `make report` measures what accuracy costs on this machine (the full run of
# `mlx3d bench accuracy`, under an hour on 2 cores) and writes the report and its
# plots into docs/accuracy/ (the committed copy comes from this target).
report: $(STAMP)
	$(VENV)/bin/mlx3d bench accuracy --out docs/accuracy

install: $(STAMP)

# `make docs` builds the documentation site into site/ (git-ignored) with MkDocs, the Material theme
# and mkdocstrings, strictly: a broken link, a page missing from the nav or a reference that does not
# resolve fails it. The API and command-line references are generated at build time
# (docs/hooks/). The tools are pinned here and installed into .venv.
DOCS_PINS := mkdocs==1.6.1 mkdocs-material==9.8.2 mkdocstrings==1.0.8 mkdocstrings-python==2.0.11
space := $(subst ,, )
DOCS_STAMP = $(VENV)/.mlx3d-docs-$(subst ==,-,$(subst $(space),_,$(DOCS_PINS)))
$(DOCS_STAMP): $(STAMP)
	$(PY) -m pip install -q $(DOCS_PINS)
	rm -f $(VENV)/.mlx3d-docs-*
	touch $@
docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict --site-dir site

test-docs:
	@$(call require_python,3.11,$(PYTHON311))
	$(MAKE) --no-print-directory docs VENV=.venv PYTHON="$(PYTHON311)" BPY=$(BPY_3.11)

# The Blender extension zip(s) in dist/ (see addon/package.py): this machine's
# platform, or `make extension PLATFORM=linux-x64,macos-arm64,windows-x64,linux-arm64`
# (or PLATFORM=all); an environment variable PLATFORM is not used.
PLATFORM =
extension: zig
	$(PY) addon/package.py $(if $(PLATFORM),--platform $(PLATFORM))

# Editable install without build isolation in a fixed build directory: the
# extension builds against the pinned mlx in this venv, and edited C++ sources
# rebuild on the next import (editable.rebuild; off in pyproject.toml because an
# isolated `pip install -e .` deletes the tools a rebuild needs).
# bpy and numpy are installed in the same pip run as the package, so all agree.
$(STAMP): pyproject.toml CMakeLists.txt
	@test -n "$(BPY)" -a -n "$(NUMPY)" || { echo "make: no bpy/numpy pin for $(VENV): its Python ($(or $(wildcard $(PY)),$(PYTHON),none found)) is not 3.11 or 3.13; pass PYTHON=/path/to/python3.X, or BPY=X.Y.Z and NUMPY=X.Y.Z" >&2; exit 1; }
	@test -x $(PY) || test -n "$(PYTHON)" || { echo "make: no Python to create $(VENV) with: pass PYTHON=/path/to/python3.11" >&2; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import subprocess, sys, tomllib; reqs = tomllib.load(open('pyproject.toml', 'rb'))['build-system']['requires']; subprocess.check_call([sys.executable, '-m', 'pip', 'install', '-q', *reqs])"
	$(PY) -m pip install -q --no-build-isolation -C build-dir=$(BUILD_DIR) -C editable.rebuild=true -e ".[test]" "bpy==$(BPY)" "numpy==$(NUMPY)"
	rm -f $(VENV)/.mlx3d-installed*
	touch $@
