# Set-up and main jobs. Every target installs what it needs into .venv first.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install run demo test test-all lint bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: install
	$(PY) experiments/train.py experiment=quick

demo: install
	$(PY) experiments/demo_foundation.py

test: install
	$(PY) -m pytest -q

test-all: install
	$(PY) -m pytest -q -m ""

lint: install
	$(VENV)/bin/ruff check .

bench: install
	$(PY) -m dicrl_torch.bench solver --experts 2
	$(PY) -m dicrl_torch.bench solver --experts 3

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache
