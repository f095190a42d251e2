# MEDC: the two commands a newcomer runs are `make demo` and `make test`.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
QUICK ?= 0
PYTEST_ARGS ?=
# pytest-xdist workers of `make test` (tests/conftest.py keeps the ROS graph tests on one of them).
TEST_WORKERS ?= 2

.PHONY: setup demo test lint clean reproduce bench

setup:
	@bash scripts/setup.sh

demo: setup
	@source scripts/env.sh && medc-demo $(if $(filter 1,$(QUICK)),--quick,)

test: setup
	@source scripts/env.sh && ruff check . && python -m pytest -n $(TEST_WORKERS) --dist loadgroup $(PYTEST_ARGS)

lint: setup
	@source scripts/env.sh && ruff check .

bench: setup
	@source scripts/env.sh && medc-bench env && medc-bench train && medc-bench ros

reproduce: setup
	@source scripts/env.sh && medc-reproduce --scale cpu --out docs/reproduction

clean:
	rm -rf $(VENV) tools/node_modules ros_ws/build ros_ws/install ros_ws/log
