# Fresh-machine entry points; both install everything first (pinned by constraints.txt).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install demo lint test test-slow test-all bench

$(STAMP): pyproject.toml constraints.txt
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e ".[test]"
	touch $(STAMP)

install: $(STAMP)

# Main job on the embedded default: the smoke grid (all algorithms + baselines, local MLflow
# on SQLite), then the report with the paper's figures and tables in reports/smoke/.
demo: install
	$(PY) -m uavlora_rllib.tune tune_configs/smoke.yaml
	$(PY) -m analysis.report --experiment smoke --tracking-uri sqlite:///mlflow.db --out reports/smoke

# Lint, format and types, zero findings (configured in pyproject.toml): ruff's linter and its
# formatter (`ruff format` rewrites, here only checked) on the code and the tests, mypy on the
# package. CI runs it before the tests.
lint: install
	$(VENV)/bin/ruff check uavlora_rllib analysis tests
	$(VENV)/bin/ruff format --check uavlora_rllib analysis tests
	$(VENV)/bin/mypy

# What a contributor runs before every commit: everything but the tests marked `slow`
# (learning runs, whole grids, clusters). test-slow runs those; test-all runs both at once.
test: install
	$(PY) -m pytest -q -m "not slow"

test-slow: install
	$(PY) -m pytest -q -m slow

test-all: install
	$(PY) -m pytest -q

bench: install
	$(PY) -m uavlora_rllib.bench env
