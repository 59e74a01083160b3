# Quickstart targets. Each installs what it needs into a local .venv.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test deps system-deps lint format bench clean

# --no-compile: Python compiles each module it imports, once, when it first imports it;
# byte-compiling every installed module up front (numba, scipy, dask, matplotlib, OpenSeesPy …)
# costs ~40 s of CPU that most of those modules never pay back.
$(STAMP): pyproject.toml
	@$(PYTHON) -m venv $(VENV) || { echo "error: '$(PYTHON) -m venv' failed; on Debian install python3-venv"; exit 1; }
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --no-compile -e '.[dev]'
	@touch $(STAMP)

# Python writes the bytecode of what it imports into .venv and the tree (an environment that
# sets PYTHONDONTWRITEBYTECODE would have every process compile every module it imports again:
# the tests start hundreds, twins, partners and `rths-hil run` among them).
run test: export PYTHONDONTWRITEBYTECODE =

run: $(STAMP)
	$(BIN)/rths-hil run $(ARGS)

# System packages some tests need (OpenSeesPy's BLAS/LAPACK, headless Chromium): the script
# installs what is missing and returns at once (dpkg-query) when nothing is.
system-deps:
	@bash scripts/system-deps.sh

# The Python environment and the system packages side by side: two independent downloads and
# installs (pip into .venv, apt-get into the system), on a fresh machine tens of seconds each.
deps:
	@$(MAKE) --no-print-directory -j2 $(STAMP) system-deps

# Tests whose checks need the machine to run them promptly (marker "timing": a loop paced
# against the wall clock, a bound on how soon something happens) run one at a time after the
# others. The others share the cores (pytest-xdist, one file per worker), those that start
# twins, OpenSees or Chromium and wait for them as long as it takes included. The slowest
# timing tests are listed at the end (they set the length of the run).
# Exit 5 = PYTEST_ARGS selected none of one kind. numpy's OpenBLAS keeps one thread per test
# process: a pool per core in each of two workers fought over the cores (a file's tests took
# twice as long).
test: export OPENBLAS_NUM_THREADS = 1
test: deps lint
	$(BIN)/python -m pytest -q -m "not timing" -n auto --dist loadfile $(PYTEST_ARGS) || test $$? -eq 5
	$(BIN)/python -m pytest -q -m timing --durations=25 $(PYTEST_ARGS) || test $$? -eq 5
	$(BIN)/python -m pytest -q --doctest-modules --pyargs rths_hil rths_hil.drivers rths_hil.sim_backends

# ruff (style, imports, complexity, numpydoc on the public API) and mypy on rths_hil.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info runs
