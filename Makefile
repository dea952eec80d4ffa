# Two commands do all set-up on a fresh machine: `make run` and `make test`.
# Both create .venv when it is missing and (re)install the package when its sources change.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.hybridoc-installed
# Directories whose file lists decide the editable install's link tree (strict mode).
PKG_DIRS := hybridoc hybridoc/cli reference solvers solvers/contacts problems problems/library problems/scenes

.PHONY: run test test-all fuzz lint format docs bench install clean

# The main job: cross-validation of reference, transcription and gradient descent on both
# of the paper's problems; tables on stdout, figures and JSON reports in ./out.
run: $(STAMP)
	$(BIN)/hybridoc crossval single-collision --out out
	$(BIN)/hybridoc crossval multiple-collision --out out

# CI's tier: every test but those marked slow (a few minutes each), which `make test-all` adds.
test: $(STAMP)
	$(BIN)/pytest -q -p no:cacheprovider -m "not slow"

test-all: $(STAMP)
	$(BIN)/pytest -q -p no:cacheprovider

# The property tests of the judge with a hundred times more random cases (and random seeds).
fuzz: $(STAMP)
	HYBRIDOC_FUZZ=1 $(BIN)/pytest -q -p no:cacheprovider tests/test_judge_properties.py \
		--hypothesis-show-statistics

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

docs: $(STAMP)
	$(BIN)/sphinx-build -E -W --keep-going -b html docs docs/_build/html

bench: $(STAMP)
	@set -e; for f in benchmarks/bench_*.py; do echo "== $$f"; $(BIN)/python $$f; done

install: $(STAMP)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch: the CPU build 2.13.0 on disk first, so the dependency range is already satisfied
# and pip never fetches the multi-gigabyte CUDA build.
$(STAMP): $(BIN)/python pyproject.toml $(PKG_DIRS)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check torch==2.13.0
	$(BIN)/python -m pip install --quiet --disable-pip-version-check \
		-e ".[dev]" --config-settings editable_mode=strict
	touch $(STAMP)

clean:
	rm -rf $(VENV) build *.egg-info docs/_build out
