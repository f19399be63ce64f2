# wvr: `make demo` and `make test` are all a new user needs; both set everything up first.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT ?= demo-out

# Offscreen rendering without a display: MuJoCo and VTK (pyvista) through EGL on Mesa.
export MUJOCO_GL := egl
export PYOPENGL_PLATFORM := egl
export VTK_DEFAULT_OPENGL_WINDOW := vtkEGLRenderWindow
# Two cores: keep BLAS from oversubscribing them under pytest and Dask.
export OMP_NUM_THREADS ?= 1

# chromium: Debian's browser, driven by Playwright in the station's tests (never `playwright install`).
DEB_PACKAGES := libegl1 libopengl0 libgl1 libgles2 libegl-mesa0 libgl1-mesa-dri libglx-mesa0 chromium

.PHONY: setup deb demo test bench clean

setup: deb $(STAMP)

# Installs only the Debian packages that are missing (idempotent; needs root or sudo).
deb:
	@missing=$$(for p in $(DEB_PACKAGES); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q "ok installed" || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages (offscreen rendering, the station's test browser): $$missing"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev]"
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/wvr demo --out $(OUT)
	@echo "open $(OUT)/report.md"

# One worker per core; a file stays on one worker so its module fixtures are built once; the
# notebooks run in the same pool.
test: setup
	$(PY) -m pytest -q -n auto --dist loadfile --nbmake tests notebooks
	d=$$(mktemp -d); NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet --site-dir $$d; s=$$?; rm -rf $$d; exit $$s

bench: setup
	$(PY) benchmarks/run.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
