# Two commands do everything on a fresh machine:  make demo  |  make test
# Python 3.11 exactly: pybullet ships binary wheels only for cp311 (a source build takes 7+ minutes).

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO   := demo_out
export TERGODIC_CACHE_DIR ?= $(CURDIR)/.cache/tergodic

.PHONY: setup test demo bench sysdeps data clean

# open3d needs libusb, libGL and libgomp at import time; install them from apt when missing.
sysdeps:
	@missing=""; \
	for pair in libusb-1.0.so.0:libusb-1.0-0 libGL.so.1:libgl1 libgomp.so.1:libgomp1; do \
	  lib=$${pair%%:*}; pkg=$${pair##*:}; \
	  ldconfig -p 2>/dev/null | grep -q "$$lib" || missing="$$missing $$pkg"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system libraries for open3d:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -ne 0 ] && SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing >/dev/null; \
	fi

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), "tergodic needs Python 3.11 (pybullet wheels are cp311-only); found " + sys.version.split()[0]'
	$(MAKE) sysdeps
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	@# open3d and open3d-cpu write the same files: a venv made before the switch drops open3d first
	@if [ "$$(uname -sm)" = "Linux x86_64" ] && $(BIN)/pip show -q open3d >/dev/null 2>&1; then $(BIN)/pip uninstall -y -q open3d; fi
	$(BIN)/pip install -q -e '.[test]'
	@touch $(STAMP)

setup: $(STAMP)

# The suite on every core (pytest-xdist; worksteal: an idle worker takes tests from a busy one, so one long file does not leave a core idle);
# TEST_JOBS=0 runs it in one process. The slowest tests are listed at the end.
# make test leaves out the tests marked long (end-to-end coverage and robot runs of a minute or more each,
# listed in pyproject.toml's markers); make test-all runs every test.
TEST_JOBS ?= auto
test: setup
	$(BIN)/python -m pytest -n $(TEST_JOBS) --dist worksteal --durations=15 -m "not long"

.PHONY: test-all
test-all: setup
	$(BIN)/python -m pytest -n $(TEST_JOBS) --dist worksteal --durations=15

# The main job on the built-in data: the procedurally built bowl with an X in data/bowl.
# Basis (cached), 1000 kinematic exploration steps logged to MCAP, then the replay's plots.
demo: setup
	$(BIN)/tergodic precompute data/bowl
	$(BIN)/tergodic explore data/bowl --robot kinematic --steps 1000 --start random --seed 0 --out $(DEMO)/kinematic --overwrite
	$(BIN)/tergodic replay $(DEMO)/kinematic --plot $(DEMO)/kinematic/plots --html $(DEMO)/kinematic/report.html --overwrite
	@echo "demo: see $(DEMO)/kinematic/summary.json, $(DEMO)/kinematic/report.html and the PNGs in $(DEMO)/kinematic/plots/"

# The README's images from the demo run; the report's screenshot is taken by a headless Chromium, installed
# from apt when missing (Debian's package chromium, Ubuntu's chromium-browser). tests/test_report_browser.py
# opens the report in the same browser, and skips when none is installed.
.PHONY: images chromium
chromium:
	@if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null && ! command -v google-chrome >/dev/null; then \
	  echo "installing a headless Chromium for the report's screenshot"; \
	  SUDO=""; [ "$$(id -u)" -ne 0 ] && SUDO=sudo; \
	  $$SUDO apt-get update -qq && (DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium >/dev/null \
	    || DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium-browser >/dev/null); \
	fi

images: demo chromium
	cp $(DEMO)/kinematic/plots/cloud_target.png docs/img/demo.png
	cp $(DEMO)/kinematic/plots/ergodicity.png docs/img/demo_ergodicity.png
	@browser=$$(command -v chromium || command -v chromium-browser || command -v google-chrome || true); \
	if [ -n "$$browser" ]; then \
	  $$browser --headless --disable-gpu --no-sandbox --hide-scrollbars --screenshot=docs/img/report.png --window-size=1400,900 \
	    file://$(CURDIR)/$(DEMO)/kinematic/report.html 2>/dev/null; \
	else echo "images: no chromium could be installed; docs/img/report.png left as it is"; fi

# Every benchmark, BLAS pinned to one thread; each prints medians and ratios against the reference.
BENCH_ENV := OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 TERGODIC_NO_PROGRESS=1
BENCHES   := precompute step coverage explore_reference logging robot sweep
bench: setup
	@for b in $(BENCHES); do echo "== benchmarks/$$b.py"; $(BENCH_ENV) $(BIN)/python benchmarks/$$b.py || exit 1; done

# Regenerate the project's own built-in clouds in data/.
data: setup
	for obj in bowl plate mug; do $(BIN)/tergodic capture --synthetic $$obj --marking X --seed 0 --out data/$$obj --overwrite; done

# numba's kernels (explorer, robot) into its disk cache, so the first explore starts at once (~35 s cold, ~5 s when current).
.PHONY: warm
warm: $(STAMP)
	@$(BIN)/python -m tergodic_cli.warm
setup: warm

clean:
	rm -rf $(DEMO) .cache .pytest_cache
