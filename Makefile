# Two commands set up everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

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

test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q -ra

lint: $(STAMP)
	$(PY) -m ruff check .

bench: $(STAMP)
	$(VENV)/bin/followbus bench bus

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
