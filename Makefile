# Two commands do all set-up on a fresh machine: `make run` and `make test`.
# Both create .venv when it is missing and (re)install the package when its sources change.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.hybridoc-installed
# Directories whose file lists decide the editable install's link tree (strict mode).
PKG_DIRS := hybridoc hybridoc/cli hybridoc/workflows hybridoc/workflows/validation hybridoc/workflows/datasets hybridoc/workflows/training hybridoc/workflows/policy_format reference reference/shooting reference/search solvers solvers/contacts solvers/transcription solvers/gd problems problems/library problems/scenes

# Python writes the bytecode of what it imports (__pycache__) even where the environment
# says not to: with the install's --no-compile (below), a process that cannot write it would
# compile torch's modules again at every start.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: run test test-all fuzz lint format docs docs-check screenshots bench bench-summary install clean

# The main job: cross-validation of reference, transcription and gradient descent on both
# of the paper's problems; tables on stdout, figures and JSON reports in ./out.
run: $(STAMP)
	$(BIN)/hybridoc crossval single-collision --out out
	$(BIN)/hybridoc crossval multiple-collision --out out

# CI's tier: every test but those marked slow (they test a scale rather than a behaviour),
# which `make test-all` adds. One worker per usable core (pytest-xdist); the 15 slowest
# tests are listed so that creep shows.
PYTEST := $(BIN)/pytest -q -p no:cacheprovider -n auto --durations=15
test: $(STAMP)
	$(PYTEST) -m "not slow"

test-all: $(STAMP)
	$(PYTEST)

# The property tests of the judge with a hundred times more random cases (and random seeds),
# and issue #21's property of the reference against gd's multi-start (300 random scenes at
# about 20 s each on 2 busy cores: the longest part, well over an hour).
fuzz: $(STAMP)
	HYBRIDOC_FUZZ=1 $(BIN)/pytest -q -p no:cacheprovider tests/test_judge_properties.py \
		tests/test_reference_global_property.py --hypothesis-show-statistics

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

# The site with every tutorial executed in full.
docs: $(STAMP)
	$(BIN)/sphinx-build -E -W --keep-going -b html docs docs/_build/html

# CI's docs check: every page built, warnings as errors, without running the tutorials
# (make test has just run each of them, in its quick mode).
docs-check: $(STAMP)
	HYBRIDOC_DOCS_EXECUTE=0 $(BIN)/sphinx-build -E -W --keep-going -q -b html docs docs/_build/html-check

# Headless Chromium screenshots of the landing page and every tutorial page of the built
# docs, in docs/_build/screenshots (not part of `make test`; installs Debian's chromium when
# it is missing). Run `make docs` first.
CHROMIUM ?= /usr/bin/chromium
SHOTS := docs/_build/screenshots
SHOT_SIZE ?= 1280,2400
screenshots:
	@test -f docs/_build/html/index.html || { echo "run 'make docs' first"; exit 2; }
	@test -x $(CHROMIUM) || { apt-get update -qq && apt-get install -y -qq chromium; }
	@mkdir -p $(SHOTS)
	@set -e; for page in docs/_build/html/index.html docs/_build/html/auto_tutorials/[0-9][0-9]_*.html; do \
		name=$$(basename $$page .html); \
		profile=$$(mktemp -d); \
		timeout 120 $(CHROMIUM) --headless --no-sandbox --disable-gpu \
			--disable-background-networking --disable-component-update --disable-sync \
			--no-first-run --hide-scrollbars --user-data-dir=$$profile \
			--virtual-time-budget=5000 --window-size=$(SHOT_SIZE) \
			--screenshot=$(SHOTS)/$$name.png file://$(CURDIR)/$$page 2>/dev/null; \
		rm -rf $$profile; \
		echo "$(SHOTS)/$$name.png"; \
	done

bench: $(STAMP)
	@set -e; for f in benchmarks/bench_*.py; do \
		[ "$$f" = benchmarks/bench_all.py ] && continue; echo "== $$f"; $(BIN)/python $$f; done

# Issue #18's one table: every speed target beside its measured value, in one run.
bench-summary: $(STAMP)
	$(BIN)/python benchmarks/bench_all.py

install: $(STAMP)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch: the CPU build 2.13.0 on disk first, so the dependency range is already satisfied
# and pip never fetches the multi-gigabyte CUDA build. --no-compile: pip's byte-compilation
# of every installed module (torch and sympy alone are ~5000) took 80 of the install's 107 s
# on 2 busy cores; Python compiles what is imported instead, once (below).
PIP := $(BIN)/python -m pip install --quiet --disable-pip-version-check --no-compile
$(STAMP): $(BIN)/python pyproject.toml $(PKG_DIRS)
	$(PIP) torch==2.13.0
	$(PIP) -e ".[dev]" --config-settings editable_mode=strict
	touch $(STAMP)

clean:
	rm -rf $(VENV) build *.egg-info docs/_build out
