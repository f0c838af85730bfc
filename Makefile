# Two entry points for a fresh machine: `make demo` (main job) and `make test` (test suite).
# Both create .venv and install pinned dependencies first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo lint test test-slow bench bench-design clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -c constraints.txt -e ".[dev]"
	$(BIN)/python -m ros_nodes.interfaces.build > $(VENV)/interfaces-build.log 2>&1 \
		|| (tail -n 40 $(VENV)/interfaces-build.log; exit 1)
	$(BIN)/python -c "from design_engine.physics.native.build import main; main()"
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/metarig demo --out runs/demo

# The fast suite on every core (at most 4 workers; one DDS domain and one process per worker),
# a file's tests on one worker so module fixtures are built once, the longest files first
# (tests/file_seconds.json, see tests/conftest.py); benchmarks/bench_suite.py times exactly
# this command.
PYTEST_ARGS ?= -n auto --maxprocesses 4 --dist loadfile --no-loadscope-reorder

lint: install
	$(BIN)/ruff check .

test: install
	$(BIN)/python -m pytest $(PYTEST_ARGS)

test-slow: install
	$(BIN)/python -m pytest $(PYTEST_ARGS) --runslow

# Speed-accuracy studies: charts + JSON in runs/bench (about 2 hours on 2 cores).
bench: install
	$(BIN)/metarig bench work-precision --out runs/bench
	$(BIN)/metarig bench speedup --out runs/bench
	for s in focusing-contact-24x16 precompressed-contact-12x10 focus-vs-protect-24x18 \
	         reprogram-location-24x18; do $(BIN)/metarig bench speedup --scene $$s --out runs/bench; done
	$(BIN)/metarig bench stability --out runs/bench
	$(BIN)/metarig bench stability --contact --out runs/bench
	$(BIN)/metarig bench throughput --out runs/bench
	$(BIN)/python benchmarks/bench_core.py --out runs/bench

clean:
	rm -rf $(VENV) runs

# Design loop: every task preset at its spec budget (hours on 2 cores; resumable with --resume).
bench-design: install
	$(BIN)/python benchmarks/bench_design.py --out runs/bench-design
