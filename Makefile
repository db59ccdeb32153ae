# `make demo` and `make test` work on a fresh machine: each creates .venv on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup demo test test-unit locate-example clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet -e '.[test]'
	touch $@

demo: setup
	$(BIN)/toptag demo --duration 60 --report demo-report.json

locate-example: setup
	$(BIN)/toptag locate --camera examples/rsu-sw-960x720.json --vehicle examples/bus-17.json examples/*.jpg

test: setup
	$(BIN)/python -m pytest -q

test-unit: setup  # the fast tier: pure code, no network, no child process
	$(BIN)/python -m pytest -q -m unit

clean:
	rm -rf $(VENV) build *.egg-info
