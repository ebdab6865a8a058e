# skyloop: `make demo`, `make test`, `make bench` set themselves up on a fresh machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# Exact torch pin: a looser range pulls a multi-GB CUDA build on a CPU-only machine.
TORCH  := torch==2.13.0

.PHONY: demo test test-docker bench lint clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install -q "$(TORCH)"
	$(PY) -m pip install -q -e ".[test]"
	touch $(STAMP)

# The process graph (sim, perception, policy, bridge, record) in lockstep, shipped policy.
demo: $(STAMP)
	$(PY) -m skyloop up --scenario valley --episodes 5 --lockstep --log-dir out/logs

# Two workers, a test file each (module fixtures stay whole): most tests wait on real
# processes, so two at a time finish the suite in ~0.63 of the serial time on 2 cores.
# Then the tests with wall-clock deadlines (marker "timing"), alone: under a second
# worker's load a node's 2-s exit was seen to take 2.02 s. TEST_WORKERS=0: no workers.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile -m "not docker and not timing" --durations=25
	$(PY) -m pytest -m "timing and not docker" --durations=5

# The stack in containers (tests/stack/test_docker_compose.py: builds the image, minutes on a
# fresh machine); needs a Docker engine and compose v2 (docker/setup-engine.sh), else skips.
test-docker: $(STAMP)
	$(PY) -m pytest -m docker --durations=10

bench: $(STAMP)
	$(PY) -m pip install -q -e ".[bench]"
	test -x .venv-peers/bin/python || ($(PYTHON) -m venv .venv-peers && .venv-peers/bin/pip install -q PyFlyt)
	$(PY) -m skyloop bench --json benchmarks/results/latest.json

lint: $(STAMP)
	$(PY) -m ruff check .

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
