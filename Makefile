# Two entry points for a fresh clone: `make demo` (the main job) and `make test`.
# Each builds its own virtual environment in .venv and installs what it needs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test bench venv clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

# Until the fleet runtime exists, the main job is the paper's estimator comparison (Figs. 4 and 5).
demo: $(STAMP)
	$(VENV)/bin/usv-lab compare --runs 100 --seed 2024

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(VENV)/bin/usv-lab bench --seed 7

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
