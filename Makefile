# Every target creates .venv and installs what it needs by itself (fresh machine, CI).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install system-deps c-toolchain demo test test-slow hil bench paper lint wheel-check clean

install: $(STAMP)

# The system libraries the gige extra builds against and loads (apt; installed when missing and
# we are root, else named): PyGObject, pycairo and libaravis (docs/lab-setup.md).
system-deps:
	@bash .ci/system-deps

# torch is pinned: 2.13.0 is a CPU build on these machines, an unpinned torch pulls CUDA.
# The install compiles udan._kernels (setup.py, udan/_kernels.c): a C compiler and the headers
# of $(PYTHON) come first, from apt when missing (CI runs as root on a fresh machine).
$(STAMP): pyproject.toml setup.py udan/_kernels.c
	@$(MAKE) --no-print-directory c-toolchain
	@bash .ci/system-deps
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[train,scale,dev,web,gige]'
	touch $(STAMP)

HAS_HEADERS = $(PYTHON) -c 'import os, sys, sysconfig; \
  sys.exit(not os.path.isfile(os.path.join(sysconfig.get_path("include"), "Python.h")))'
c-toolchain:
	@command -v cc >/dev/null && $(HAS_HEADERS) && exit 0; \
	command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ] || \
	  { echo "make: udan._kernels needs a C compiler and Python's headers: apt-get install gcc python3-dev" >&2; exit 2; }; \
	DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends gcc libc6-dev python3-dev \
	  || { apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends gcc libc6-dev python3-dev; }

# A real headless browser for the live page's tests: Debian's chromium (Playwright drives it; its
# own browser download is not used). Installed with apt when missing (CI runs as root).
CHROMIUM := /usr/bin/chromium
$(CHROMIUM):
	@command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ] || \
	  { echo "make: the live page's tests need Debian's chromium: apt-get install chromium"; exit 1; }
	DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium \
	  || { apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium; }

# The edge runtime against the virtual camera and the mock fleet, with the bundled policy.
demo: $(STAMP)
	@mkdir -p out/demo
	$(VENV)/bin/udan-edge --sim --cars 5 --duration 30 --report out/demo/report.json \
	  --telemetry out/demo/telemetry.jsonl --video out/demo/run.mp4

test: $(STAMP) $(CHROMIUM)
	$(PY) -m pytest -q -m "not slow"

test-slow: $(STAMP) $(CHROMIUM)
	$(PY) -m pytest -q -m slow

# The hardware-in-the-loop suite, long cases included (the fast ones also run in `make test`).
hil: $(STAMP) $(CHROMIUM)
	$(PY) -m pytest -q -m hil

bench: $(STAMP)
	@mkdir -p out/bench
	@for b in bench/*.py; do name=$$(basename $$b .py); echo "== $$b"; \
	  $(PY) -P $$b > out/bench/$$name.json || exit 1; cat out/bench/$$name.json; done

# The paper's tables and figures, regenerated from the committed models beside the paper's
# numbers: docs/results.md and docs/results/ (udan-paper; minutes on one core, see its output).
paper: $(STAMP)
	$(VENV)/bin/udan-paper --out docs/results.md

# The wheel as users get it: udan.* alone, installed without torch into a fresh venv, the
# commands run from an empty folder (.ci/wheel-check says each step).
wheel-check: $(STAMP)
	PYTHON=$(PYTHON) BUILD_PYTHON=$(PY) bash .ci/wheel-check

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
