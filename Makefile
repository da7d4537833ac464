# The README's two commands: `make demo` runs the main job end to end on the
# built-in default scene; `make test` runs the test suite. Both create the
# virtual environment and build the compiled extension on first use.
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.mlx3d-installed

.PHONY: demo test bench install extension

demo: $(STAMP)
	$(VENV)/bin/mlx3d demo --out demo_out

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/ply_io.py
	$(PY) bench/knn.py
	$(PY) bench/from_points.py
	$(PY) bench/blender_io.py

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
