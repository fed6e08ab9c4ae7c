# wiggly: two set-up commands (see README): `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin
STAMP   = $(VENV)/.installed
TESTED  = $(VENV)/.installed-test

.PHONY: demo test venv kernels system-render-deps system-test-deps blender blender-addon cholmod bench lint docs clean

$(STAMP): pyproject.toml
	@echo "[make] installing wiggly into $(VENV) (a minute or two the first time)"
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e .
	touch $(STAMP)

## The test tools (pytest, ruff, Playwright, Ray, ...) on top of the core install.
$(TESTED): $(STAMP)
	@echo "[make] installing the test tools into $(VENV)"
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(TESTED)

venv: $(STAMP)

## Compile the warp's numba kernels into their on-disk cache (about a minute on two cores
## the first time, with a live elapsed-time line; 1 s when cached).
kernels: $(STAMP)
	@$(BIN)/python -c "import logging, time; t = time.perf_counter(); \
	  logging.basicConfig(format='[wiggly] %(message)s', level=logging.INFO); \
	  from wiggly.progress import reporting; shown = reporting(); shown.__enter__(); \
	  from wiggly.warp.kernels import ensure_compiled; ensure_compiled(); \
	  from wiggly.drive.unwarp import compile_kernels; compile_kernels(); \
	  print(f'[wiggly] warp kernels ready ({time.perf_counter() - t:.1f} s)')"

## Animate the bundled critter and say where the results are (again: its own files replaced).
demo: $(STAMP) kernels system-render-deps
	$(BIN)/wiggly demo --overwrite

## Offscreen rendering (previews) uses EGL with Mesa's software rasterizer.  Installed with
## apt-get when missing and running as root; otherwise wiggly explains what to install.
system-render-deps:
	@if ! dpkg -s libegl1 libgl1-mesa-dri >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "[make] installing libegl1 libgl1-mesa-dri (offscreen rendering)"; \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
	      libegl1 libgl1-mesa-dri >/dev/null) || echo "[make] could not install them"; \
	  else echo "[make] libegl1/libgl1-mesa-dri missing and not root: previews may fail"; fi; \
	fi

## Lint and run the test suite (installs what the tests need).
test: $(TESTED) kernels system-render-deps system-test-deps blender
	$(BIN)/ruff check src tests benchmarks scripts blender
	$(BIN)/python -m pytest -q -n 2 -p no:cacheprovider

## System packages the tests use when available: headless Chromium (browser editor tests)
## and Node.js/npm (Khronos glTF validator).  Installed with apt-get when running as root;
## otherwise those tests skip with a reason.
system-test-deps:
	@missing=""; \
	command -v chromium >/dev/null 2>&1 || missing="$$missing chromium chromium-driver"; \
	command -v npm >/dev/null 2>&1 || missing="$$missing nodejs npm"; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "[make] installing system packages:$$missing"; \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null) \
	      || echo "[make] could not install$$missing; the tests that need them will skip"; \
	  else \
	    echo "[make] not root or no apt-get: tests needing$$missing will skip"; \
	  fi; \
	fi
	@$(BIN)/python -c "import playwright" 2>/dev/null || $(BIN)/python -m pip install --quiet playwright

## Blender as a Python module (PyPI bpy 5, Python 3.11 only, ~800 MB, ~20 s) in its own venv,
## since bpy pins its own numpy: tests/test_blender.py imports our .glb/.usd in it (and skips
## with the reason when it is missing).
BLENDER_VENV ?= .venv-blender
blender:
	@if ! $(BLENDER_VENV)/bin/python -c "import bpy" >/dev/null 2>&1; then \
	  echo "[make] installing bpy (Blender as a Python module) into $(BLENDER_VENV)"; \
	  ($(PYTHON) -m venv $(BLENDER_VENV) && \
	   $(BLENDER_VENV)/bin/python -m pip install --quiet "bpy>=5,<6") \
	  || echo "[make] could not install bpy (it needs Python 3.11); the Blender test will skip"; \
	fi

## The Blender extension (blender/wiggly_blender) as an installable zip in $(BLENDER_ADDON_DIR)/
## (Blender 4.2+: Edit > Preferences > Get Extensions > Install from Disk); docs/blender.md.
BLENDER_ADDON_DIR ?= dist
blender-addon:
	@$(PYTHON) blender/build_extension.py $(BLENDER_ADDON_DIR)

## Optional speed-up: CHOLMOD sparse Cholesky (SuiteSparse) on OpenBLAS for large bodies
## (on a 105k-tet box: factorization 24 s with the reference BLAS, 2.6 s with OpenBLAS).
cholmod: $(STAMP)
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  (dpkg -s libsuitesparse-dev libopenblas0-pthread >/dev/null 2>&1 || (apt-get update -qq && \
	   DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libsuitesparse-dev \
	   libopenblas0-pthread >/dev/null)) && \
	  $(BIN)/python -m pip install --quiet "scikit-sparse==0.4.16" \
	  || echo "[make] CHOLMOD not available; wiggly uses cholespy"; \
	else echo "[make] CHOLMOD needs root for libsuitesparse-dev; wiggly uses cholespy"; fi

## Benchmarks of the issues' performance targets (prints tables).
bench: $(TESTED) cholmod
	$(BIN)/python benchmarks/run_all.py

## The documentation site (Sphinx, MyST, furo: the `docs` extra) into docs/_build/html;
## warnings are errors.
docs: $(STAMP)
	@$(BIN)/python -c "import sphinx, myst_parser, furo" 2>/dev/null \
	  || $(BIN)/python -m pip install --quiet -e ".[docs]"
	$(BIN)/python -m sphinx -W --keep-going -q -b html docs docs/_build/html
	@echo "[make] docs: docs/_build/html/index.html"

lint: $(TESTED)
	$(BIN)/ruff check src tests benchmarks scripts blender

clean:
	rm -rf $(VENV) $(BLENDER_VENV) build dist *.egg-info .pytest_cache .ruff_cache wiggly-demo
