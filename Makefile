# Set-up contract: `make demo` and `make test` work on a fresh clone (Python 3.11+).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install demo test test-long bench docs clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "rollingstar needs Python 3.11+; set PYTHON=python3.11")'
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/rollingstar demo

# Lint and import order first (ruff, configured in pyproject.toml); pytest exit code 5 (no tests
# collected) must fail the run. Two pytest workers (pytest-xdist), each test file on one of them so
# that a module's shared fixtures (a study run once for its tests) are computed once.
test: $(STAMP)
	$(PY) -m ruff check --no-cache .
	@$(PY) -m pytest -q -p no:cacheprovider -n 2 --dist loadfile --durations=10 -m "not long_study"; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; exit 1; fi; exit $$rc

# The whole-study checks (each up to a minute or more of CPU: the adversarial identification set, the
# rendered and real cameras, the he2021b and fu2022 reproductions, the quick run of every benchmark
# line), which .ci/run runs after `make test`.
test-long: $(STAMP)
	@$(PY) -m pytest -q -p no:cacheprovider -n 2 --dist loadfile -m long_study; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; exit 1; fi; exit $$rc

bench: $(STAMP)
	$(PY) benchmarks/speed.py

# The documentation site (Sphinx, MyST Markdown, API reference from the docstrings), warnings as
# errors; .ci/run builds it. Open docs/_build/html/index.html.
DOCS_STAMP := $(VENV)/.docs-installed
$(DOCS_STAMP): $(STAMP)
	$(PY) -m pip install -q -e '.[test,docs]'
	@touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	$(VENV)/bin/sphinx-build -E -W --keep-going -q -b html docs docs/_build/html
	@echo "built docs/_build/html/index.html ($$(find docs/_build/html -name '*.html' | wc -l) pages)"

clean:
	rm -rf $(VENV) build *.egg-info docs/_build docs/_generated docs/reference/_api
