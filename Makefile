# `make serve` and `make test` work on a fresh machine: both first build .venv (Python 3.11+ as python3)
# and install the project into it; the stamp re-installs only when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed.stamp

.PHONY: serve test bench venv

serve: $(STAMP)
	$(VENV)/bin/kinetix serve

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/pytest

bench: $(STAMP)
	$(VENV)/bin/kinetix bench engine

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --disable-pip-version-check -e '.[dev]'
	touch $@
