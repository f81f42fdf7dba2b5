# Two commands on a fresh machine:
#   make run   - set up, then run the main job (see README)
#   make test  - set up, then run the test suite
# Packaging (docs/packaging.md): make wheels (dist/), make wheel-check (the wheels in a clean environment).
# Each creates .venv when missing and installs what it needs; a second call skips the install.
PY        := .venv/bin/python
STAMP     := .venv/.installed
SUDO      := $(shell [ "$$(id -u)" = "0" ] || echo sudo)
# Debian packages: what the Python dependencies need at import time (pyrealsense2 -> libusb), and a C compiler for
# the runtime's compiled kernels (without one the install still works, with refinement in numpy).
DEB_PKGS  := libusb-1.0-0 gcc libc6-dev
RUN_OUT   ?= out/demo
BUNDLE    ?= models/epal-default
DIST      ?= dist
# the clean virtual environment and scratch folder of `make wheel-check` (rebuilt on every call)
CHECK_DIR := build/wheel-check
# the built-in recording: 8 frames of the generator's occluded warehouse, deterministic (seed 7)
DEMO_REC  := $(RUN_OUT)/recording

.PHONY: run test setup sys-deps clean wheels wheel-check

setup: $(STAMP)

# setup.py and the C source: the editable install builds the compiled kernels in place (runtime/*.so)
$(STAMP): pyproject.toml setup.py runtime/kernels.c
	@$(MAKE) --no-print-directory sys-deps
	@test -x $(PY) || python3 -m venv .venv
	@# torch first, pinned: it resolves to the local CPU wheel, not the multi-GB CUDA build.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[export,realsense,oakd,serve,dev]'
	@touch $@

sys-deps:
	@missing=""; for p in $(DEB_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq $$missing >/dev/null; \
	fi

run: $(STAMP) $(DEMO_REC)/.done
	$(PY) -m pallet6d.runtime.cli run --frame camera --bundle $(BUNDLE) --source bop:$(DEMO_REC) --format text --out $(RUN_OUT)/overlays

$(DEMO_REC)/.done: | $(STAMP)
	$(PY) -m pallet6d.runtime.cli sim --preset virtual-occluded --frames 8 --seed 7 --out $(DEMO_REC) --preview
	@touch $@

test: $(STAMP)
	$(PY) -m pytest -q

# The runtime wheel and the models wheel, checked against the source tree (every module and data file in,
# nothing else). Leftovers of earlier builds are removed first: setuptools would put files from build/ and from
# an old *.egg-info/SOURCES.txt in the wheel.
wheels: | $(STAMP)
	rm -rf $(DIST) build models/build *.egg-info models/*.egg-info
	$(PY) -m pip wheel -q --no-deps -w $(DIST) . ./models
	$(PY) .ci/wheel_contents.py $(DIST)

# The wheels installed as a user installs them (with the serve extra; no editable install, no export extra, no
# torch, outside the checkout), then the same check as the Dockerfile's build: .ci/smoke-installed. The
# environment has no pip of its own (.venv's pip installs into it): only the wheels and their dependencies are in it.
wheel-check: wheels
	rm -rf $(CHECK_DIR) && python3 -m venv --without-pip $(CHECK_DIR)/venv
	$(PY) -m pip --python $(CHECK_DIR)/venv/bin/python install -q "$$(ls $(DIST)/pallet6d-*.whl)[serve]" $(DIST)/pallet6d_models-*.whl
	env -u PALLET6D_BUNDLE PATH="$(CURDIR)/$(CHECK_DIR)/venv/bin:$$PATH" .ci/smoke-installed $(CHECK_DIR)/work

clean:
	rm -rf .venv out .pytest_cache build dist models/build models/*.egg-info
