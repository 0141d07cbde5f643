# bridgeOS Cloud: `make run` starts everything, `make test` tests everything.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: run test test-fast services images lint docs bench chaos install clean deploy undeploy

## Create .venv and install the cloud, the agent, the `bridgeos` command line and the test tools (torch first: the CPU build on disk).
install: $(STAMP)
$(STAMP): pyproject.toml agent/pyproject.toml cli/pyproject.toml
	@echo "== venv: installing into $(VENV)"
	@start=$$(date +%s); \
	test -x $(PY) || $(PYTHON) -m venv $(VENV); \
	$(PY) -m pip install -q --upgrade pip setuptools wheel; \
	$(PY) -m pip install -q torch==2.13.0; \
	$(PY) -m pip install -q -e "./agent[ros2,rosbridge]" -e ./cli -e ".[test]"; \
	echo "== venv: ready in $$(( $$(date +%s) - start )) s"
	@touch $@

## Start daphne on 127.0.0.1:8000, a Celery worker (when Redis answers) and print the operator login.
run: install
	@bash scripts/run.sh

## Install and start what the tests need (PostgreSQL, Redis, dockerd + Swarm, roscore, images), then run them all.
test: install services
	@bash scripts/test.sh

## Run the tests without (re)checking services.
test-fast: install
	@bash scripts/test.sh

services:
	@bash scripts/services.sh

images:
	@bash docker/build-images.sh

## Build the stack's images and deploy docker/stack.yml on this machine's Swarm; print the URL and login (README "Deploying").
deploy:
	@bash scripts/deploy.sh

## Remove the deployed stack; its volumes stay (UNDEPLOY_ARGS=--volumes deletes them).
undeploy:
	@bash scripts/deploy.sh down $(UNDEPLOY_ARGS)

## ruff, mypy, the generated reference pages against the code, and the documentation site with --strict (broken links fail).
lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	$(PY) scripts/docs_reference.py --check
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

## Regenerate docs/reference/ from the code and build the documentation site into .data/site (mkdocs.yml).
docs: install
	$(PY) scripts/docs_reference.py
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet
	@echo "== docs: open .data/site/index.html, or run $(VENV)/bin/mkdocs serve -a 127.0.0.1:8001"

## Run every benchmark and write .data/bench/report.md beside the thesis's figures (BENCH_ARGS="--quick", "--only router", "--strict").
bench: install
	@$(PY) scripts/bench.py $(BENCH_ARGS)

## Break every real part on purpose and print what survived (benchmarks/faults.py, every scenario in full; CHAOS_ARGS="--only link").
chaos: install services
	@$(PY) benchmarks/faults.py $(CHAOS_ARGS)

clean:
	rm -rf $(VENV) .data .pytest_cache .hypothesis
