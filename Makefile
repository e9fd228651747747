# The two commands of the README: `make run` and `make test`. Each does its own set-up first
# (idempotent: a second run skips what is already installed).
PY ?= python3
TOPOLOGY ?= topologies/local.yaml
PYTEST_ARGS ?=
# The default suite runs on two pytest-xdist workers: much of it waits on processes (role start-up,
# restarts, Zenoh sessions); tests that share machine-wide daemons are grouped on one worker
# (tests/conftest.py). TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= 2

.PHONY: setup setup-test run test test-slow

setup:
	@bash scripts/setup.sh

# the suite also uses a real Slurm (slurm-wlm, munge) and LIBERO (the `libero` extra)
setup-test:
	@bash scripts/setup.sh test

run: setup
	$(PY) -m dvla up $(TOPOLOGY)

test: setup-test
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup --durations=25 $(PYTEST_ARGS)

test-slow: setup-test
	$(PY) -m pytest -q -m slow $(PYTEST_ARGS)
