# make demo | make test | make bench   (each creates .venv if missing)
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
# setuptools' notes on editable installs (one block per install) are for packagers, not for the user of `make`
EDITABLE := PYTHONWARNINGS=ignore::UserWarning $(PIP) install -q -e
# The CPU build of PyTorch for the optional `learn` extra (the `complete` stage). Override for CUDA.
TORCH_SPEC ?= torch==2.13.0
SEQ ?= demo

.PHONY: demo test bench faults lint clean-runs

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip

# one stamp per install flavour, redone when pyproject.toml changes
$(VENV)/.stamp-run: pyproject.toml | $(VENV)/bin/python
	$(PIP) install -q "$(TORCH_SPEC)"
	$(EDITABLE) ".[learn]"
	touch $@

$(VENV)/.stamp-dev: pyproject.toml | $(VENV)/bin/python
	$(PIP) install -q "$(TORCH_SPEC)"
	$(EDITABLE) ".[dev,learn,distributed]"
	touch $@ $(VENV)/.stamp-run

demo: $(VENV)/.stamp-run
	$(VENV)/bin/pipeline run all --seq $(SEQ)
	$(VENV)/bin/pipeline status --seq $(SEQ)

lint: $(VENV)/.stamp-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

# one BLAS thread per test: two threads spin against any other work on a 2-core machine (one thread is faster
# alone too)
test: lint
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(PY) -m pytest -q

bench: $(VENV)/.stamp-dev
	$(PY) -m benchmarks

faults: $(VENV)/.stamp-run
	OMP_NUM_THREADS=1 $(PY) -m benchmarks.fault_probe

clean-runs:
	rm -rf runs
