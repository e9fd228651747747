# The two commands of the README: `make run` and `make test`. Each does its own set-up first
# (idempotent: a second run skips what is already installed).
PY ?= python3
TOPOLOGY ?= topologies/local.yaml
PYTEST_ARGS ?=

.PHONY: setup setup-test run test test-slow

setup:
	@bash scripts/setup.sh

# the suite also uses a real Slurm (slurm-wlm, munge) and LIBERO (the `libero` extra)
setup-test:
	@bash scripts/setup.sh test

run: setup
	$(PY) -m dvla up $(TOPOLOGY)

test: setup-test
	$(PY) -m pytest -q $(PYTEST_ARGS)

test-slow: setup-test
	$(PY) -m pytest -q -m slow $(PYTEST_ARGS)
