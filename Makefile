# The two set-up commands of the README. Each makes its own virtual environment in .venv.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV) || { $(PYTHON) -m pip install --user virtualenv && $(PYTHON) -m virtualenv $(VENV); }
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/diffeit demo --output demo.png

# The tests run SciPy's solves (OpenBLAS) beside XLA's own threads: one BLAS thread avoids
# oversubscribing small CI machines, where threaded BLAS can run tens of times slower.
test: $(STAMP)
	$(BIN)/ruff check diffeit hw tests benchmarks examples
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m pytest

# One BLAS thread: on a small shared machine multithreaded BLAS is erratic; override for a
# dedicated one, e.g. `make bench BENCH_FLAGS=`.
BENCH_FLAGS ?= --blas-threads 1

bench: $(STAMP)
	$(BIN)/python benchmarks/forward_jacobian.py $(BENCH_FLAGS)
	$(BIN)/python benchmarks/inverse.py $(BENCH_FLAGS)
	$(BIN)/python benchmarks/scene.py $(BENCH_FLAGS)

clean:
	rm -rf $(VENV) demo.png .pytest_cache
