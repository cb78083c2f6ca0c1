PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: bench test install clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) (set PYTHON=...)"; exit 1; }
	@echo "== creating the virtual environment $(VENV) with $(PYTHON)"
	$(PYTHON) -m venv $(VENV)
	@echo "== upgrading pip"
	$(PY) -m pip install --quiet --upgrade pip
	@echo "== installing coiltrack with its bench, test and sweep extras (numpy, python-can, magpylib,"
	@echo "   matplotlib, pyigtl, pytest, scipy, cantools, filterpy, dask; about a minute on a first install)"
	$(PY) -m pip install --quiet --progress-bar off -e '.[bench,dev,sweep]'
	@echo "== installed; $(VENV)/bin/coiltrack is ready"
	touch $(STAMP)

install: $(STAMP)

bench: $(STAMP)
	@echo "== running the roetenberg-bench scenario (60 s simulated), report in bench-report.json"
	$(VENV)/bin/coiltrack bench --scenario roetenberg-bench --seed 1 --json bench-report.json

test: $(STAMP)
	@echo "== running the test suite"
	$(PY) -m pytest

clean:
	rm -rf $(VENV) build *.egg-info firmware_py/_core*.so
