# Two entry points for a fresh clone: `make demo` (the main job) and `make test`.
# Each builds its own virtual environment in .venv and installs what it needs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: demo compare test test-fast bench scenarios fleet-bench runtime-bench venv clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

# The main job: the paper's Table II fleet (four vessels, MCKF) as separate processes over Zenoh, one agent
# per vessel and the sim bridge; leaves a run folder in runs/ with every MCAP log, a plot and the metrics.
demo: $(STAMP)
	$(VENV)/bin/usv-fleet run configs/scenarios/table2_estimators.yaml --variant mckf

# The paper's estimator comparison (Figs. 4 and 5), 100 Monte Carlo runs.
compare: $(STAMP)
	$(VENV)/bin/usv-lab compare --runs 100 --seed 2024

# Everything (what .ci/run calls), about 8 minutes on 2 cores.
test: $(STAMP)
	$(PY) -m pytest -q

# The pure, in-process suite, under a minute: no fleet processes, Zenoh sessions or real-time waits
# (the tests marked `slow`; tests/conftest.py says which).
test-fast: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

bench: $(STAMP)
	$(VENV)/bin/usv-lab bench --seed 7

# Every scenario of the paper's Sec. VI-B (Tables II-IV, Figs. 7-15), about 15 minutes on 2 cores.
scenarios: $(STAMP)
	$(VENV)/bin/usv-lab scenario all

fleet-bench: $(STAMP)
	$(VENV)/bin/usv-lab fleet-bench

# The Zenoh runtime: latency, lockstep real-time factor, memory (about 2 minutes).
runtime-bench: $(STAMP)
	$(VENV)/bin/usv-lab runtime-bench

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
