# Set-up and the two everyday jobs. `make demo` and `make test` set everything up first;
# running them again only redoes what changed.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV ?= .venv
STAMP := $(VENV)/.installed
OUT ?= out/demo

.PHONY: setup demo test test-durations test-fast lint system-deps clean

system-deps:
	@scripts/system-deps.sh

$(STAMP): pyproject.toml
	@test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip
	$(VENV)/bin/python -m pip install -q -e '.[all,test,dev]'
	@touch $(STAMP)

setup: system-deps $(STAMP)

demo: setup
	$(VENV)/bin/canopy-kit demo --out $(OUT)

# Test files run in parallel, one whole file per worker (its module fixtures are made once),
# the longest first (tests/conftest.py orders them by tests/file_seconds.json; xdist would
# otherwise hand out the files with the most tests first and leave a long one for the end).
PARALLEL = -n auto --maxprocesses=4 --dist loadfile --no-loadscope-reorder

test: setup
	$(VENV)/bin/python -m pytest $(PARALLEL)

# The linter and formatter (ruff, configured in pyproject.toml); .ci/run runs it before the tests.
lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# Measures each test file's seconds (the whole suite) into the order make test follows.
test-durations: setup
	$(VENV)/bin/python -m pytest $(PARALLEL) --record-file-seconds tests/file_seconds.json

test-fast: setup
	$(VENV)/bin/python -m pytest $(PARALLEL) -m "not slow"

clean:
	rm -rf out .pytest_cache
