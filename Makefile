# Two entry points for a fresh clone: `make demo` (the main job) and `make test`.
# Each builds its own virtual environment in .venv and installs what it needs: the demo the runtime and the
# plots only, the tests everything else besides (pytest, hypothesis, filterpy, dask, the operator's tools).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
RUNTIME := $(VENV)/.installed-runtime
STAMP := $(VENV)/.installed-stamp

.PHONY: demo compare test test-fast test-pythons bench scenarios fleet-bench runtime-bench venv clean

# --no-compile: the imports compile what they use, once (10 of the first demo's 45 s went to compiling all of
# numpy, scipy and matplotlib).
$(RUNTIME): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --no-compile --disable-pip-version-check -e '.[lab]'
	touch $(RUNTIME)

$(STAMP): $(RUNTIME)
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

# The main job: the paper's Table II fleet (four vessels, MCKF) as separate processes over Zenoh, one agent
# per vessel and the sim bridge; leaves a run folder in runs/ with every MCAP log, a plot and the metrics.
demo: $(RUNTIME)
	$(VENV)/bin/usv-fleet run configs/scenarios/table2_estimators.yaml --variant mckf

# The paper's estimator comparison (Figs. 4 and 5), 100 Monte Carlo runs.
compare: $(RUNTIME)
	$(VENV)/bin/usv-lab compare --runs 100 --seed 2024

# Everything (what .ci/run calls), about 20 minutes on 2 cores.
test: $(STAMP)
	$(PY) -m pytest -q

# The core suite, under a minute on 2 cores (pytest-xdist, one worker a core): no processes, Zenoh sessions,
# real-time waits or seconds-long integration runs (the tests marked `slow`; tests/conftest.py says which).
FAST := -m "not slow" -n auto
test-fast: $(STAMP)
	$(PY) -m pytest -q $(FAST)

bench: $(STAMP)
	$(VENV)/bin/usv-lab bench --seed 7

# Every scenario of the paper's Sec. VI-B (Tables II-IV, Figs. 7-15), about 15 minutes on 2 cores.
scenarios: $(RUNTIME)
	$(VENV)/bin/usv-lab scenario all

fleet-bench: $(RUNTIME)
	$(VENV)/bin/usv-lab fleet-bench

# The Zenoh runtime: latency, lockstep real-time factor, memory (about 2 minutes).
runtime-bench: $(RUNTIME)
	$(VENV)/bin/usv-lab runtime-bench

# `make test-fast` on every other Python this project supports that the machine has, each in its own
# .venv-3.X (what .ci/run calls after `make test`): pyenv's versions/ first (its shims may not resolve
# python3.X), then PATH; one that is not there, or does not run, is skipped with a line that says so.
# Then the suite once more on the main Python under OPENBLAS_CORETYPE=Haswell: its kernels round differently
# from the SkylakeX ones of an AVX-512 machine, so no test may depend on either.
OTHER_PYTHONS ?= 3.10 3.12 3.13
test-pythons: $(STAMP)
	@for version in $(OTHER_PYTHONS); do \
	  found=""; \
	  for candidate in $$(ls -d $$(pyenv root 2>/dev/null)/versions/$$version.*/bin/python$$version 2>/dev/null | sort -V | tail -n 1) $$(command -v python$$version); do \
	    if "$$candidate" -c "" 2>/dev/null; then found=$$candidate; break; fi; \
	  done; \
	  if [ -z "$$found" ]; then echo "test-pythons: skipped Python $$version: no working python$$version on this machine"; continue; fi; \
	  echo "test-pythons: Python $$version ($$found)"; \
	  $(MAKE) --no-print-directory test-fast PYTHON=$$found VENV=.venv-$$version || exit 1; \
	done
	@echo "test-pythons: OPENBLAS_CORETYPE=Haswell on $$($(PY) --version)"
	OPENBLAS_CORETYPE=Haswell $(PY) -m pytest -q $(FAST)

clean:
	rm -rf $(VENV) .venv-3.* .pytest_cache .hypothesis
