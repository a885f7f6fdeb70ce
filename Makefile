# Two entry points on a fresh machine: `make demo` (the main job) and `make test`.
# Both create .venv and install the package with everything it needs.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test lint schemas bench clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $@

demo: $(BIN)/.installed
	$(BIN)/mergesvc demo --out results/demo

# The tests spread over the cores in groups (tests/conftest.py: a file, or the files sharing a
# session fixture, runs on one worker; the heaviest groups first; a few files test by test, to
# fill the ends); one BLAS thread per worker, since the workers fill the cores.
test: $(BIN)/.installed
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $$(( $$(nproc) + 1 )) --dist loadgroup --no-loadscope-reorder

lint: $(BIN)/.installed
	$(BIN)/ruff check mergesvc tests

schemas: $(BIN)/.installed
	$(BIN)/mergesvc schemas schemas

bench: $(BIN)/.installed
	$(BIN)/mergesvc bench match --peer --out results/bench_match.json
	$(BIN)/mergesvc bench paper --out results/paper
	$(BIN)/mergesvc bench link --out results/bench_link.json
	$(BIN)/mergesvc bench uncertainty --out results
	$(BIN)/mergesvc bench generalize --seeds 3 --out results/generalize.json
	$(BIN)/mergesvc bench merge --out results/bench_merge.json
	$(BIN)/mergesvc bench cost --baseline-factors 500 --out results/bench_cost.json --figure results/bench_cost.png
	$(BIN)/mergesvc bench fuzz --out results/fuzz100k.json
	$(BIN)/mergesvc bench qaplib --out results/qaplib.json

clean:
	rm -rf $(VENV) examples results .pytest_cache
