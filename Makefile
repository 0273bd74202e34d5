# The two commands: `make demo` and `make test`. Both create the virtualenv on first use.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test lint benchmarks install clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' || { echo "error: $(PYTHON) is not Python 3.11 or newer: name one, e.g. make PYTHON=python3.12 $(MAKECMDGOALS)" >&2; exit 1; }
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/arcade demo

# Unit, property and workflow tests share the cores (one worker per test file, so per-file
# fixtures are built once); the integration tests run alone, one at a time: the realtime
# ones assert on timing, and the others gain nothing on the workers (they pass there
# since lockstep buses are lossless, but under load their flights use more CPU: README).
test: lint
	$(PY) -m pytest -q -m "not integration" -n 2 --dist loadfile --durations=15
	$(PY) -m pytest -q -m integration --durations=15 tests/integration

# ruff, then the import contract of design §2 (pyproject.toml's [tool.importlinter]).
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports --no-cache

# Regenerates BENCHMARKS.md from measurements on this machine (slow: minutes).
benchmarks: $(STAMP)
	$(VENV)/bin/arcade bench report --out BENCHMARKS.md

clean:
	rm -rf $(VENV) runs .pytest_cache
