# Two commands do everything on a fresh machine:
#   make demo   set up, then run the daemon on a virtual bus fed by a simulated drive
#   make test   set up, then run the test suite
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# Numba's compiled kernels are cached here (portable target, so the SocketCAN VM can load
# the cache the host built).
export NUMBA_CACHE_DIR ?= $(CURDIR)/.numba_cache
export NUMBA_CPU_NAME ?= generic

.PHONY: demo test lint bench setup clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $@

demo: setup
	$(BIN)/slipd run --demo

test: setup
	$(BIN)/pytest -q

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python -m benchmarks.codec
	$(BIN)/python -m benchmarks.replay
	$(BIN)/python -m benchmarks.estimators
	$(BIN)/python -m benchmarks.daemon_latency

clean:
	rm -rf $(VENV) .numba_cache .pytest_cache .ruff_cache
