# Fresh-machine entry points; both install everything first (pinned by constraints.txt).
VENV ?= .venv
# An extra index to take torch from before the rest (e.g. https://download.pytorch.org/whl/cpu, PyTorch's CPU
# wheels): PyPI's Linux torch is the CUDA build, GBs more. Empty: pip's own configuration decides.
TORCH_INDEX ?=
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install demo lint test test-slow test-all bench

$(STAMP): pyproject.toml constraints.txt
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(if $(TORCH_INDEX),$(PY) -m pip install -q -c constraints.txt torch --extra-index-url $(TORCH_INDEX))
	$(PY) -m pip install -q -c constraints.txt -e ".[test]"
	touch $(STAMP)

install: $(STAMP)

# Main job on the embedded default: the smoke grid (all algorithms + baselines, local MLflow
# on SQLite), then the report with the paper's figures and tables in reports/smoke/. Run again, it
# continues the grid where it stopped (--resume: a finished one reruns nothing) and redraws the report.
demo: install
	$(PY) -m uavlora_rllib.tune tune_configs/smoke.yaml $(if $(wildcard ray_results/smoke),--resume)
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
