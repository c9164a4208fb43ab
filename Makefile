# The two README commands: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.vi3-installed

.PHONY: test test-fast demo bench lint venv clean

$(STAMP): setup.py setup.cfg pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check torch==2.13.0
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	@touch $(STAMP)

venv: $(STAMP)

lint: $(STAMP)
	$(VENV)/bin/ruff check .

test: $(STAMP) lint
	$(PY) -m pytest -q tests

# The unit tests (tests marked slow left out): under a minute on two cores, for everyday work.
test-fast: $(STAMP) lint
	$(PY) -m pytest -q -m "not slow" tests

demo: $(STAMP)
	$(VENV)/bin/vi3 demo

bench: $(STAMP)
	$(VENV)/bin/vi3 bench all

clean:
	rm -rf $(VENV) .cache out *.egg-info
