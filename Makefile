# The two commands: `make demo` and `make test`. Both set everything up first.
VENV := .venv
BIN := $(VENV)/bin
DEMO_OUT ?= demo_out

.PHONY: setup demo test test-fast bench lint clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(BIN)/workbench demo -o $(DEMO_OUT) --overwrite

test: setup
	@bash scripts/setup.sh --browser
	$(BIN)/python -m pytest -q -n auto --dist loadgroup --durations=15

test-fast: setup
	$(BIN)/python -m pytest -q -n auto --dist loadgroup -m "not slow"

bench: setup  # BENCH_ARGS="--preset city": the 1 km² city end to end (about two hours)
	$(BIN)/python benchmarks/run.py $(BENCH_ARGS)

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .ruff_cache
