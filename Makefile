# Two commands set up everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
TEST_STAMP := $(VENV)/.test-stamp

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml requirements-peers.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev,peers]'
	$(PY) -m pip install --quiet --no-deps -r requirements-peers.txt
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/followbus demo --domain auto
	@echo "the followbus command: source $(VENV)/bin/activate (then followbus --help), or run $(VENV)/bin/followbus"

# The suite runs every test it has: dora-rs (the `bench` extra, ~126 MB of wheels) for the bench bus test
# against dora, installed here rather than for `make demo`, which does not need it.
$(TEST_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e '.[bench]'
	touch $(TEST_STAMP)

# Two workers; each test module runs whole on one of them, and the modules whose live graphs judge timing run
# one after another (tests/conftest.py, TIMING_SENSITIVE_MODULES).
test: $(TEST_STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q -ra --durations=25 -n 2 --dist loadgroup

lint: $(STAMP)
	$(PY) -m ruff check .

bench: $(STAMP)
	$(VENV)/bin/followbus bench bus

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
