# Two commands for a newcomer: `make demo` (the main job) and `make test` (everything CI runs).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test lint bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	$(BIN)/python -m compileall -q appliance calibration   # bytecode once: PYTHONDONTWRITEBYTECODE may be set
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/viper demo

lint: $(STAMP)
	$(BIN)/ruff check appliance calibration tests bench
	$(BIN)/mypy

test: lint
	$(BIN)/python -m pytest

bench: $(STAMP)
	$(BIN)/python bench/run_all.py

clean:
	rm -rf $(VENV) build *.egg-info
