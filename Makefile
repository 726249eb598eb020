# Two entry points for a fresh machine: `make demo` and `make test`.
# Both create (or reuse) .venv and install the package from pyproject.toml into it.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-fast test-all test-deps bench-faults bench-discovery lint docs venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,lint]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/thermal-edge demo

# the suite: everything but the long sweeps marked slow; the SocketCAN VM tests run when the
# packages of `make test-deps` are there, else they skip and say why (the suite installs nothing)
test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not slow"

# quick local runs: no VM, no slow tests
test-fast: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -m "not slow and not vm"

# everything, the slow sweeps included (discovery over all effects, installed service, VM bench)
test-all: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q

# Debian packages of the system-level tests, for a CI machine or a developer's (as root, once; the
# suite itself never installs anything and skips those tests naming this target):
# the SocketCAN VM of tests/vm (qemu, a distribution kernel with vcan, a static busybox, can-utils;
# tests/vm/vmrun.py APT_PACKAGES) and systemd-analyze with the commands the units run
# (tests/deploy/test_systemd.py), and promtool for the alert rules and dashboard queries (prometheus;
# tests/deploy/test_prometheus.py). Installs only the packages that are missing: nothing when all are there.
TEST_DEBS := qemu-system-x86 linux-image-amd64 busybox-static can-utils systemd kmod iproute2 prometheus
test-deps:
	@missing=$$(for p in $(TEST_DEBS); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q 'ok installed' || echo $$p; done); \
	missing=$$(echo $$missing); \
	if [ -z "$$missing" ]; then echo "test-deps: all installed ($(TEST_DEBS))"; exit 0; fi; \
	echo "test-deps: apt-get install $$missing"; \
	export DEBIAN_FRONTEND=noninteractive; \
	apt-get install -y -q --no-install-recommends $$missing || \
	  { apt-get update -q && apt-get install -y -q --no-install-recommends $$missing; }

# benchmarks that need the checkout (benchmarks/README.md); `thermal-edge bench` runs the others.
# BENCH_ARGS passes options on, e.g. make bench-faults BENCH_ARGS="--only crash --json"
BENCH_ARGS ?=
bench-faults: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m benchmarks.faults $(BENCH_ARGS)

bench-discovery: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m benchmarks.discovery $(BENCH_ARGS)

# the code's own declarations checked: ruff (style, imports, bugs) and mypy (types)
lint: $(STAMP)
	$(BIN)/ruff check thermal_edge tests benchmarks
	$(BIN)/mypy

# the manual: docs/ built by Sphinx into build/docs/html; a warning (a broken reference, a stale page, a
# docstring that does not parse) fails the build; the reference pages are generated from their sources
DOCS_STAMP := $(VENV)/.docs-installed
$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[docs]'
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m sphinx -W --keep-going -n -q -b html docs build/docs/html
	@echo "the manual: build/docs/html/index.html"

clean:
	rm -rf $(VENV) build *.egg-info
