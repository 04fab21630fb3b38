# The two commands of the README. Each installs what it needs into .venv first (pinned by constraints.txt).
PYTHON ?= python3
VENV ?= .venv
BIN = $(VENV)/bin

.PHONY: main test lint benchmarks matrix headline claims slurm-check

# The embedded default, conf/experiment/main.yaml: one generated variant and the two real datasets (cube, elbow), every model at
# budget=quick, scored on val and test, then one results table.
main: $(VENV)/.installed
	$(BIN)/python generate.py variant=frictioncubes_0.5
	$(BIN)/python train.py -m experiment=main
	$(BIN)/python -m contactbench.evaluation.report outputs/main

# The whole benchmark at one budget, conf/experiment/matrix.yaml: {mujoco_default, sysid, sysid_mjx, gnn, hybrid, residual, and the
# other engines untuned and identified: bullet_default, sysid_bullet, drake_default, sysid_drake} x 34
# synthetic variants (the paper's 22 and the 12 of its future work) + the real cube and elbow, scored on val and test, then the report. The hybrid model skips multi-body
# variants with one line each; `make matrix SEEDS=3` fits every cell with seeds 0, 1, 2 and the report shows their mean
# and 95% interval; the report writes the repository's results/$(BUDGET).csv, one row a cell (the committed results).
# `make matrix BUDGET=paper ARGS='hydra/launcher=cluster hydra.launcher.partition=<yours>'` sends the same
# sweep to a Slurm cluster (docs/CLUSTER.md).
BUDGET ?= quick
SEEDS ?= 1
ARGS ?=
matrix: $(VENV)/.installed
	$(BIN)/python generate.py -m 'variant=glob(*)'
	$(BIN)/python train.py -m experiment=matrix budget=$(BUDGET) $(if $(filter-out 1,$(SEEDS)),'seed=range($(SEEDS))') $(ARGS)
	$(BIN)/python -m contactbench.evaluation.report outputs/matrix/$(BUDGET) --results results

# The README's headline in one sitting, conf/experiment/real.yaml: every model on the real cube and elbow at budget=quick
# (into the matrix's folder), the report's results/quick.csv, and the README's table written from that file alone.
headline: $(VENV)/.installed
	$(BIN)/python train.py -m experiment=real $(ARGS)
	$(BIN)/python -m contactbench.evaluation.report outputs/matrix/quick --results results
	$(BIN)/python -m contactbench.evaluation.headline

# The paper's findings in one sitting, conf/experiment/claims.yaml: its three methods and untuned MuJoCo on its 22
# variants at budget=quick (into the matrix's folder), the report's results/quick.csv (other sittings' rows kept) and
# results/quick_claims.md, each finding judged from that file.
claims: $(VENV)/.installed
	$(BIN)/python generate.py -m 'variant=glob([bouncycubes_*,frictioncubes_*,polyhedra_*,multicubes_*])'
	$(BIN)/python train.py -m experiment=claims $(ARGS)
	$(BIN)/python -m contactbench.evaluation.report outputs/matrix/quick --results results

# A real single-node Slurm on this machine (root; apt-get install slurm-wlm munge): a small matrix through
# hydra/launcher=cluster, one GNN job killed with scontrol requeue and resumed, the report counting every job done.
slurm-check: $(VENV)/.installed
	$(BIN)/python cluster/slurm_check.py

# One worker per core, each taking whole test files (module fixtures are built once, servers' ports stay apart).
test: $(VENV)/.installed
	$(BIN)/python -m pytest -q -n auto --dist loadfile

# ruff's lint rules and formatting ([tool.ruff] in pyproject.toml); .ci/run runs it before the tests.
lint: $(VENV)/.installed
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

benchmarks: $(VENV)/.installed
	for script in benchmarks/*.py; do $(BIN)/python $$script || exit 1; done

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip==25.3
	$(BIN)/pip install --quiet -c constraints.txt -e .
	touch $@
