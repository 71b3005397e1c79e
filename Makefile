# The two set-up commands of the README. Each makes its own virtual environment in .venv.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench docs lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV) || { $(PYTHON) -m pip install --user virtualenv && $(PYTHON) -m virtualenv $(VENV); }
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,bench,notebooks,sweeps,docs]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/diffeit demo --output demo.png

# No thread variables: the tests and benchmarks run in the environment users have (diffeit
# limits BLAS threads itself, only while it computes). `make bench BENCH_FLAGS="--blas-threads 1"`
# pins the measuring processes instead.
test: $(STAMP)
	$(BIN)/ruff check diffeit hw tests benchmarks examples experiments
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -n 2 --dist worksteal --durations=20  # both cores; the 20 slowest tests at the end

BENCH_FLAGS ?=

bench: $(STAMP)
	$(BIN)/python benchmarks/forward_jacobian.py $(BENCH_FLAGS)
	$(BIN)/python benchmarks/inverse.py $(BENCH_FLAGS)
	$(BIN)/python benchmarks/scene.py $(BENCH_FLAGS)
	$(BIN)/python benchmarks/fit.py $(BENCH_FLAGS)
	$(BIN)/python benchmarks/memory_bound.py
	$(BIN)/python benchmarks/calibration.py
	$(BIN)/python benchmarks/session_layouts.py
	$(BIN)/python benchmarks/contact_drift.py
	$(BIN)/python benchmarks/touches.py
	$(BIN)/python benchmarks/rest_anchors.py
	$(BIN)/python benchmarks/slides.py
	$(BIN)/python benchmarks/surface.py

# The documentation site, into site/ (tests/test_docs.py builds it with --strict in `make test`).
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict

clean:
	rm -rf $(VENV) demo.png .pytest_cache
