# `make serve` and `make test` work on a fresh machine: both first build .venv (Python 3.11+ as python3)
# and install the project into it; the stamp re-installs only when pyproject.toml changes.
# ARGS goes to the command: `make serve ARGS="--port 9000"`, `make test ARGS="tests/kinetix"`,
# `make bench ARGS="--sizes s"`.
# TEST_WORKERS: pytest-xdist processes for `make test` (CI's machine has 2 cores; each worker compiles and holds its
# own JAX programs, ~1-2 GB, so not one per core on a big machine). --dist loadfile keeps a file's tests in one
# worker, in order: some reuse what an earlier test of their file computed. TEST_WORKERS=0 runs in this process.
PYTHON ?= python3
TEST_WORKERS ?= 2
ARGS ?=
VENV := .venv
STAMP := $(VENV)/.installed.stamp

.PHONY: serve test bench venv

serve: $(STAMP)
	$(VENV)/bin/kinetix serve $(ARGS)

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/pytest -n $(TEST_WORKERS) --dist loadfile $(ARGS)

bench: $(STAMP)
	$(VENV)/bin/kinetix bench engine $(ARGS)

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --disable-pip-version-check -e '.[dev]'
	touch $@
