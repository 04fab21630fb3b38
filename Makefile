# The two commands of the README. Each installs what it needs into .venv first (pinned by constraints.txt).
PYTHON ?= python3
VENV ?= .venv
BIN = $(VENV)/bin

.PHONY: main test benchmarks

# The embedded default: one generated variant and the real cube, every model at budget=quick, scored on val and
# test, then one results table.
MAIN_MODELS = mujoco_default,mujoco_fixed,sysid,gnn,hybrid
main: $(VENV)/.installed
	$(BIN)/python generate.py variant=frictioncubes_0.5
	$(BIN)/python train.py -m model=$(MAIN_MODELS) variant=frictioncubes_0.5,contactnets_cube budget=quick test=true hydra.sweep.dir=outputs/main
	$(BIN)/python -m contactbench.evaluation.report outputs/main

test: $(VENV)/.installed
	$(BIN)/python -m pytest -q

benchmarks: $(VENV)/.installed
	for script in benchmarks/*.py; do $(BIN)/python $$script || exit 1; done

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip==25.3
	$(BIN)/pip install --quiet -c constraints.txt -e .
	touch $@
