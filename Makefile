# Two entry points for a fresh machine: `make demo` and `make test`.
# Both create (or reuse) .venv and install the package from pyproject.toml into it.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-fast test-all lint docs venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,lint]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/thermal-edge demo

# the suite: everything but the long sweeps marked slow; the SocketCAN VM tests run when a VM
# can be had (root + apt), else they skip and say why
test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not slow"

# quick local runs: no VM, no slow tests
test-fast: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -m "not slow and not vm"

# everything, the slow sweeps included (discovery over all effects, installed service, VM bench)
test-all: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q

# the code's own declarations checked: ruff (style, imports, bugs) and mypy (types)
lint: $(STAMP)
	$(BIN)/ruff check thermal_edge tests
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
