# The README's commands. Each installs what is missing, then runs; a second
# run skips what is already there.
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
# Debian packages: libusb for Open3D, EGL/Mesa for headless OpenGL, Xvfb for window tests, Chromium
# for the web viewer's tests (driven by Playwright, which downloads no browser), Node.js and npm for
# the export tests' validators (tests/npm, pinned in its package-lock.json).
DEB_PACKAGES := libusb-1.0-0 libgomp1 libgl1 libegl1 libegl-mesa0 libgl1-mesa-dri xvfb xauth chromium nodejs
SYSDEPS_STAMP := $(VENV)/.sysdeps
INSTALL_STAMP := $(VENV)/.installed
NPM_STAMP := tests/npm/node_modules/.installed
DEMO_DIR ?= demo
BENCH_DIR ?= bench
KITTI_DIR ?= ../shared/data/kitti06
KITTI_OUT ?= $(DEMO_DIR)/kitti06

.PHONY: demo kitti test bench setup sysdeps clean

setup: $(INSTALL_STAMP)

$(SYSDEPS_STAMP):
	@missing=$$(for p in $(DEB_PACKAGES); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || echo $$p; done); \
	if [ -n "$$missing" ]; then \
		echo "installing Debian packages: $$missing"; \
		SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
		$$SUDO apt-get update -q && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q $$missing; \
	fi
	@command -v npm >/dev/null || { SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q npm; }
	@[ -x $(BIN)/python ] || $(PYTHON) -m venv $(VENV)
	@touch $@

# uv installs the same packages as pip in a fraction of the time (pip remains if uv cannot).
$(INSTALL_STAMP): $(SYSDEPS_STAMP) pyproject.toml
	$(BIN)/python -m pip install -q --upgrade pip uv
	$(BIN)/python -m uv pip install -q --python $(BIN)/python -e '.[dev,cluster]' \
		|| $(BIN)/python -m pip install -q -e '.[dev,cluster]'
	@touch $@

demo: $(INSTALL_STAMP)
	$(BIN)/bbcity demo --out $(DEMO_DIR)

# A KITTI odometry sequence (calib.txt, poses.txt, a stereo pair of image folders) end to end:
# every 4th frame held out of the cloud and the textures, and scored against its real image.
kitti: $(INSTALL_STAMP)
	[ -d $(KITTI_OUT)/dataset ] || $(BIN)/bbcity import kitti $(KITTI_DIR) --out $(KITTI_OUT)/dataset
	$(BIN)/bbcity recon $(KITTI_OUT)/dataset --out $(KITTI_OUT)/work --min-depth 3 --max-depth 80 --holdout 4
	$(BIN)/bbcity build $(KITTI_OUT)/work --out $(KITTI_OUT)/model
	$(BIN)/bbcity eval $(KITTI_OUT)/model $(KITTI_OUT)/dataset --cloud $(KITTI_OUT)/work/cloud.ply \
		--workprecision-depths --panel-width 960 --out $(KITTI_OUT)/eval

$(NPM_STAMP): $(SYSDEPS_STAMP) tests/npm/package-lock.json
	npm ci --prefix tests/npm --no-audit --no-fund --loglevel=error
	@touch $@

# Two pytest workers (pytest-xdist), a test file each at a time: a file's module fixtures are made once.
test: $(INSTALL_STAMP) $(NPM_STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

bench: $(INSTALL_STAMP)
	$(BIN)/bbcity bench --out $(BENCH_DIR)

clean:
	rm -rf $(VENV) $(DEMO_DIR) $(BENCH_DIR) *.egg-info
