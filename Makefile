# mrcert -- `make help` lists the targets.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
MRCERT := $(VENV)/bin/mrcert
PROFILE ?= quick
STAMP := $(VENV)/.installed
PORT ?= 5000
# The MLflow UI's address: `make ui` serves there and the tables' links point there.
export MRCERT_UI_URL := http://127.0.0.1:$(PORT)
# The store: MRCERT_OUTPUTS when set (as mrcert reads it), else outputs/.
OUTPUTS ?= $(or $(MRCERT_OUTPUTS),outputs)
# Threads for tests and benchmarks (the reference machine has 2 cores).
THREADS ?= 2
# Device for the benchmarks: cpu, or cuda on a machine with a GPU.
DEVICE ?= cpu

.DEFAULT_GOAL := help
.PHONY: help install demo figures reproduce-tables learning-curve side-by-side test test-full test-gpu bench ui server clean lint

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-12s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	@bash .ci/system-deps
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP) ## create .venv and install mrcert with its dependencies (idempotent)

demo: $(STAMP) ## quick pipeline: data, two small models, certify + attack a subset, print the table
	$(MRCERT) -m experiment=demo task=train
	$(MRCERT) -m experiment=demo task=certify,smooth,attack
	$(MRCERT) -m task=tables task.experiment=demo

# A fresh demo store for the README's pictures (removed and remade by make figures).
FIGURES ?= $(OUTPUTS)/figures

figures: $(STAMP) ## the README's pictures from a fresh demo store: the method overview and the MLflow runs page
	rm -rf $(FIGURES)
	MRCERT_OUTPUTS=$(abspath $(FIGURES)) $(MAKE) --no-print-directory demo
	cp $(FIGURES)/tables/method_overview.png docs/method_overview.png
	MRCERT_OUTPUTS=$(abspath $(FIGURES)) $(MRCERT) task=ui task.port=5077 task.screenshot=$(abspath docs/mlflow_runs.png)

# The reproduction's experiment (conf/experiment/reproduce_<profile>.yaml) and its evidence page.
REPRODUCTION = reproduce_$(PROFILE)
PAGE ?= docs/results.md
# ATTACKS=sequential: the attack stage runs sequential PREDICT, and the tables read those runs.
ATTACKS ?= fixed
$(if $(filter-out fixed sequential,$(ATTACKS)),$(error ATTACKS=$(ATTACKS) is not allowed: fixed or sequential))
ATTACK_SETTING = $(if $(filter sequential,$(ATTACKS)),++per_task.attack.sequential=true)
PAGE_TABLES = $(MRCERT) -m task=tables profile=$(PROFILE) task.show_paper=true task.page=$(PAGE) \
  $(if $(ATTACK_SETTING),'task.overrides=[$(ATTACK_SETTING)]')

reproduce-tables: $(STAMP) ## every table and figure of the paper and the evidence page (PROFILE=quick: 2 CPU cores; paper: a GPU; ATTACKS=sequential); finished work is skipped
	$(MRCERT) -m experiment=$(REPRODUCTION) task=train
	$(MRCERT) -m experiment=tabletop profile=$(PROFILE) task=train
	$(MRCERT) -m experiment=$(REPRODUCTION) task=certify,smooth
	$(MRCERT) -m experiment=$(REPRODUCTION) task=attack attack.k=5,100 $(ATTACK_SETTING)
	$(MRCERT) -m experiment=$(REPRODUCTION) task=certify task.sequential=true
	$(MRCERT) -m experiment=$(REPRODUCTION) task=attack attack.k=5,100 task.sequential=true
	$(MRCERT) -m experiment=tabletop profile=$(PROFILE) task=smooth,attack
	$(PAGE_TABLES)

side-by-side: $(STAMP) ## pixel-wise smoothing, bound propagation and image enumeration beside camera motion smoothing (docs/results.md; after make reproduce-tables' certify stage)
	$(MRCERT) -m experiment=side_by_side task=train
	$(MRCERT) -m experiment=side_by_side task=certify
	$(MRCERT) -m experiment=reproduce_quick task=certify motion=tz,rx model.variant=augmented \
	  'model.trained_for={name:pixelwise,sigma:0.25},{name:pixelwise,sigma:0.5}'  # motion smoothing on each pixel-noise model
	$(MRCERT) -m experiment=reproduce_quick task=certify motion=tz,rx model.variant=augmented task.skip=5 \
	  method=bound_propagation method.half_width=0.00001,0.0001,0.001,0.01 \
	  'model.trained_for={name:camera_motion},{name:pixelwise,sigma:0.25},{name:pixelwise,sigma:0.5}'  # deterministic, on each model
	$(MRCERT) -m experiment=reproduce_quick task=certify motion=tz model.variant=augmented task.skip=5 \
	  method=enumeration method.half_width=0.00001,0.0001,0.001,0.01 \
	  'model.trained_for={name:camera_motion},{name:pixelwise,sigma:0.25},{name:pixelwise,sigma:0.5}'  # exact, on each model
	$(PAGE_TABLES)

learning-curve: $(STAMP) ## the learning curve: test accuracy by training poses, separation rule, seed (small CNN, ResNet-18)
	$(MRCERT) -m experiment=learning_curve task=train
	$(MRCERT) -m experiment=learning_curve_any task=train
	$(MRCERT) -m experiment=learning_curve_resnet18 task=train
	$(PAGE_TABLES)

test: $(STAMP) ## the fast test suite (about 12 min on 2 cores): one pytest worker per thread, test files shared out
	OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 $(PY) -m pytest -q -n $(THREADS) --dist loadfile

test-full: $(STAMP) ## every test, the slow ones too
	OMP_NUM_THREADS=$(THREADS) NUMBA_NUM_THREADS=$(THREADS) $(PY) -m pytest -q -m ''

test-gpu: $(STAMP) ## the CUDA tests (skipped without a GPU)
	OMP_NUM_THREADS=$(THREADS) NUMBA_NUM_THREADS=$(THREADS) $(PY) -m pytest -q -m cuda -rs

bench: $(STAMP) ## benchmarks, each beside a reference measured in the same run (DEVICE=cuda for the GPU path)
	$(PY) benchmarks/projection.py --threads $(THREADS) --device $(DEVICE)
	$(PY) benchmarks/certify.py --threads $(THREADS) --device $(DEVICE)
	$(PY) benchmarks/verify.py --threads $(THREADS) --device $(DEVICE)
	$(PY) benchmarks/enumeration.py --threads $(THREADS) --device $(DEVICE)
	$(PY) benchmarks/train.py --threads $(THREADS) --device $(DEVICE)
	$(PY) benchmarks/sequential.py

ui: $(STAMP) ## MLflow UI on the project's store, opened on the experiment's runs (PORT=... to change)
	MRCERT_OUTPUTS=$(abspath $(OUTPUTS)) $(MRCERT) task=ui task.port=$(PORT)

server: $(STAMP) ## MLflow tracking server on a local SQLite database (for tracking=server)
	$(VENV)/bin/mlflow server --backend-store-uri sqlite:///$(abspath $(OUTPUTS))/mlflow-server.db \
	  --artifacts-destination $(abspath $(OUTPUTS))/mlartifacts-server --host 127.0.0.1 --port $(PORT)

lint: $(STAMP) ## ruff
	$(VENV)/bin/ruff check mrcert tests benchmarks

clean: ## remove outputs and caches (keeps .venv)
	rm -rf $(OUTPUTS) .pytest_cache .ruff_cache
	find . -name __pycache__ -not -path './$(VENV)/*' -prune -exec rm -rf {} +
