# The two commands of the README. Each installs what it needs into .venv first (pinned by constraints.txt).
PYTHON ?= python3
VENV ?= .venv
BIN = $(VENV)/bin

.PHONY: main test benchmarks

main: $(VENV)/.installed
	$(BIN)/python -m contactbench.main

test: $(VENV)/.installed
	$(BIN)/python -m pytest -q

benchmarks: $(VENV)/.installed
	for script in benchmarks/*.py; do $(BIN)/python $$script || exit 1; done

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip==25.3
	$(BIN)/pip install --quiet -c constraints.txt -e .
	touch $@
