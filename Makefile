# scalesteer: `make demo` runs the OpenMM villin demo (`make demo PORT=8001` on another port,
# `make demo ARGS="--no-browser --device cpu"` with any `scalesteer demo --help` option);
# `make test` runs the whole suite (ruff and mypy, then pytest and node --test).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PIP := $(BIN)/python -m pip
NPM_DIR := client_web

.PHONY: demo test check format schema bench bench-tables client chromium clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip

$(VENV)/.demo-installed: pyproject.toml | $(BIN)/python
	$(PIP) install -q -e ".[demo]"
	touch $@

$(VENV)/.dev-installed: pyproject.toml | $(BIN)/python
	$(PIP) install -q -e ".[dev]"
	touch $@ $(VENV)/.demo-installed

# npm dependencies of the dashboard, pinned by package-lock.json
client:
	@if [ -f $(NPM_DIR)/package.json ]; then \
	  if [ ! -f $(NPM_DIR)/node_modules/.installed ] || [ $(NPM_DIR)/package-lock.json -nt $(NPM_DIR)/node_modules/.installed ]; then \
	    (cd $(NPM_DIR) && npm ci --no-audit --no-fund --loglevel=error) && touch $(NPM_DIR)/node_modules/.installed; \
	  fi; \
	fi

# Browser tests drive Debian's Chromium; as root it is installed here, otherwise they are skipped.
chromium:
	@if command -v chromium >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = "0" ]; then \
	  apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >/dev/null; \
	else \
	  echo "note: browser tests need Debian's chromium (sudo apt-get install chromium); skipping them"; \
	fi

PORT ?=
ARGS ?=
demo: $(VENV)/.demo-installed client
	$(BIN)/scalesteer demo $(if $(PORT),--port $(PORT)) $(ARGS)

# lint and types first: a style or type error fails the suite like a failing test
test: check client chromium
	@$(BIN)/python -m pytest; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: treating as failure"; exit 1; fi; \
	if [ $$rc -ne 0 ]; then exit $$rc; fi
	@if [ -d $(NPM_DIR)/test ]; then node --test $(NPM_DIR)/test/; fi

check: $(VENV)/.dev-installed
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

format: $(VENV)/.dev-installed
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

schema: $(VENV)/.dev-installed
	$(BIN)/python -m protocol.schema -o docs/protocol.schema.json

bench: $(VENV)/.dev-installed
	$(BIN)/python benchmarks/render_bench.py --quick

# the numbers tables of benchmarks/README.md, remade from benchmarks/results/ (standard library only)
bench-tables:
	$(PYTHON) -m benchmarks.tables

clean:
	rm -rf $(VENV) $(NPM_DIR)/node_modules .hypothesis
