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

# One worker per core (tests/conftest.py gives each one torch thread); a module's tests
# that share an expensive fixture run in one worker (xdist_group marks). The slowest tests
# are listed at the end.
PYTEST := $(PY) -m pytest -q -n auto --dist loadgroup --durations=15

test: install
	$(PYTEST)

test-all: install
	$(PYTEST) -m ""

lint: install
	$(VENV)/bin/ruff check .

bench: install
	$(PY) -m dicrl_torch.bench solver --experts 2
	$(PY) -m dicrl_torch.bench solver --experts 3
	$(PY) -m dicrl_torch.bench sac

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache
