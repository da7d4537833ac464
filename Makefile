# The README's two commands: `make demo` runs the main job end to end in Blender
# on the built-in default scene; `make test` runs the test suite. Both create the
# virtual environment and build the compiled extension on first use.
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.mlx3d-installed

.PHONY: demo test bench bench-scenes report install extension

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

test: $(STAMP)
	$(PY) -m pytest -q

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

# The Blender extension zip(s) in dist/ (see addon/package.py).
extension: $(STAMP)
	$(PY) addon/package.py

# Editable install without build isolation: the extension builds against the
# pinned mlx in this venv, and edited C++ sources rebuild on the next import.
$(STAMP): pyproject.toml CMakeLists.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import subprocess, sys, tomllib; reqs = tomllib.load(open('pyproject.toml', 'rb'))['build-system']['requires']; subprocess.check_call([sys.executable, '-m', 'pip', 'install', '-q', *reqs])"
	$(PY) -m pip install -q --no-build-isolation -e ".[test]"
	touch $@
