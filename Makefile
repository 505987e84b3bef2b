# pae: two commands on a fresh clone: `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
TORCH_PINS := torch==2.14.1 torchvision==0.29.1

.PHONY: help venv demo test test-all lint bench clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*##' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-10s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml setup.py
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q $(TORCH_PINS)
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)  ## create .venv and install pae with its dev tools

demo: $(STAMP)  ## full pipeline on the embedded synthetic benchmark, prints the results table
	@if [ -e outputs/demo ]; then kept=outputs/demo-$$(date +%Y%m%d-%H%M%S); \
	  mv outputs/demo $$kept && echo "the previous demo's outputs are kept in $$kept"; fi
	@start=$$(date +%s); $(VENV)/bin/pae-train experiment=demo && \
	  echo "demo finished in $$(( $$(date +%s) - start )) s; outputs/demo holds metrics.json, checkpoints and TensorBoard logs"

test: $(STAMP)  ## fast test suite (slow end-to-end tests: make test-all)
	$(PY) -m pytest -q

test-all: $(STAMP)  ## every test, the slow ones included
	$(PY) -m pytest -q -m ''

lint: $(STAMP)  ## ruff
	$(VENV)/bin/ruff check src tests experiments
	$(VENV)/bin/ruff format --check src tests experiments

bench: $(STAMP)  ## benchmarks: one JSON object of bench/... figures
	$(PY) -m pae.bench

clean:  ## remove run outputs (keeps .venv)
	rm -rf outputs .pytest_cache
