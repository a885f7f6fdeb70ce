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
	$(BIN)/mergesvc example examples/kitti --family kitti --seed 0
	$(BIN)/mergesvc match --map examples/kitti/map.json --submap examples/kitti/submap.json
	$(BIN)/mergesvc match --map examples/kitti/map.json --submap examples/kitti/submap.json --json

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q

lint: $(BIN)/.installed
	$(BIN)/ruff check mergesvc tests

schemas: $(BIN)/.installed
	$(BIN)/mergesvc schemas schemas

bench: $(BIN)/.installed
	$(BIN)/mergesvc bench match --out results/bench_match.json

clean:
	rm -rf $(VENV) examples results .pytest_cache
