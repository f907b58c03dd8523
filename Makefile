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

.PHONY: demo test lint bench setup clean realdata

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

# The worked example of README "Bring your own recorded data": the real Ferrari 250 LM run
# (../shared/realdata) imported onto slipd's bus and evaluated against its INS truth.
REALDATA ?= ../shared/realdata/revs_250lm/revs_250lm.csv
REVS_PROFILE := examples/revs_250lm/ferrari_250lm.toml
realdata: setup
	mkdir -p runs
	$(BIN)/slipd import $(REALDATA) --profile $(REVS_PROFILE) --time t_s:s \
	    --map ax_cog_mps2=ax,ay_cog_mps2=ay,yaw_rate_radps=yaw_rate,steer_road_rad=steer \
	    --derive wheel-speeds --speed vx_mps:m/s \
	    --truth beta=beta_rad,vx=vx_mps,vy=vy_mps,yaw_rate=yaw_rate_radps \
	    --out runs/revs_250lm.log
	$(BIN)/slipd eval runs/revs_250lm.log --profile $(REVS_PROFILE) --out runs/revs_250lm.eval.json

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python -m benchmarks.codec
	$(BIN)/python -m benchmarks.replay
	$(BIN)/python -m benchmarks.fleet
	$(BIN)/python -m benchmarks.estimators
	$(BIN)/python -m benchmarks.formats
	$(BIN)/python -m benchmarks.sim_variants
	$(BIN)/python -m benchmarks.identify
	$(BIN)/python -m benchmarks.daemon_latency

clean:
	rm -rf $(VENV) .numba_cache .pytest_cache .ruff_cache
