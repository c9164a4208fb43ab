# The two README commands: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.vi3-installed

.PHONY: test test-fast demo bench lint venv clean

# Installs the test extra and, unless the venv's Python already imports an rclpy from outside the venv (a sourced
# ROS 2, whose own packages are then used: mixing the two breaks both), the ROS 2 Jazzy wheels (extra ros) for vi3_node.
# `make venv ROS_WHEELS=no` leaves the wheels out.
ROS_WHEELS ?= auto

$(STAMP): setup.py setup.cfg pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check torch==2.13.0
	@extras=test; \
	if [ "$(ROS_WHEELS)" != no ] && ! $(PY) -c "import sys, rclpy; sys.exit(rclpy.__file__.startswith(sys.prefix))" \
		2>/dev/null; then extras=test,ros; fi; \
	echo "$(PY) -m pip install -e '.[$$extras]'"; \
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[$$extras]"
	@$(PY) -c "import rclpy; print('vi3_node runs on the rclpy in', rclpy.__file__.rsplit('/', 2)[0])" 2>/dev/null \
		|| echo "vi3_node: no rclpy (the node's tests will skip; see README)"
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
