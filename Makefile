# mrcert -- `make help` lists the targets.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PORT ?= 5000
OUTPUTS ?= outputs
# Threads for tests and benchmarks (the reference machine has 2 cores).
THREADS ?= 2

.DEFAULT_GOAL := help
.PHONY: help install demo test test-full bench ui clean lint

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-12s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	@ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || { \
	  echo "open3d needs the system library libusb-1.0: run 'sudo apt-get install libusb-1.0-0' (Debian/Ubuntu)"; exit 1; }
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP) ## create .venv and install mrcert with its dependencies (idempotent)

demo: $(STAMP) ## render the built-in test scene's contact sheet, tracked in MLflow
	$(VENV)/bin/mrcert task=render

test: $(STAMP) ## the fast test suite (< 10 min on 2 cores)
	OMP_NUM_THREADS=$(THREADS) NUMBA_NUM_THREADS=$(THREADS) $(PY) -m pytest -q

test-full: $(STAMP) ## every test, the slow ones too
	OMP_NUM_THREADS=$(THREADS) NUMBA_NUM_THREADS=$(THREADS) $(PY) -m pytest -q -m ''

bench: $(STAMP) ## benchmarks, each beside a reference measured in the same run
	$(PY) benchmarks/projection.py --threads $(THREADS)

ui: $(STAMP) ## MLflow UI on the project's store (http://127.0.0.1:5000, PORT=... to change)
	$(VENV)/bin/mlflow ui --backend-store-uri sqlite:///$(abspath $(OUTPUTS))/mlflow.db \
	  --default-artifact-root $(abspath $(OUTPUTS))/mlartifacts --host 127.0.0.1 --port $(PORT)

lint: $(STAMP) ## ruff
	$(VENV)/bin/ruff check mrcert tests benchmarks

clean: ## remove outputs and caches (keeps .venv)
	rm -rf $(OUTPUTS) .pytest_cache .ruff_cache
	find . -name __pycache__ -not -path './$(VENV)/*' -prune -exec rm -rf {} +
