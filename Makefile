# zagv developer commands. `make run` and `make test` work on a fresh machine with Python >= 3.11.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install run test test-long lint bench schema clean

$(STAMP): pyproject.toml setup.py services/nav/_astar.c services/common/_gridops.c services/localization/_refine.c \
		services/nav/_navops.c services/common/_pybuffer.h
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: install
	$(BIN)/zagv up --sim

test: install
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/python -m proto.schema --check
	$(BIN)/python -m proto.keytable --check
	$(BIN)/python -m tools.servicedoc --check
	$(BIN)/python -m pytest -q -rs

test-long: install
	$(BIN)/python -m pytest -q -rs -m long

lint: install
	$(BIN)/ruff check .
	$(BIN)/mypy

bench: install
	$(BIN)/zagv bench

schema: install
	$(BIN)/python -m proto.schema

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache
