PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: bench test install docs clean

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

# the documentation site: MkDocs with the Material theme (extra `docs`), built strict (a broken
# internal link or a page missing from the nav fails it) into site/. The reference pages
# (commands, scenarios, configuration keys) are generated from the code first, into docs/reference/
# (ignored by git), and the protocol specification's message table is brought up to date.
DOCS_STAMP := $(VENV)/.docs-installed

$(DOCS_STAMP): $(STAMP)
	@echo "== installing the docs extra (mkdocs, mkdocs-material)"
	$(PY) -m pip install --quiet --progress-bar off -e '.[bench,dev,sweep,docs]'
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	@echo "== generating the reference pages into docs/reference/"
	$(PY) -m coiltrack.tools.docsgen docs/reference
	@echo "== building the site into site/"
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) build *.egg-info site firmware_py/_core*.so
