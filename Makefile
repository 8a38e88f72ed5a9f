# Two entry points: `make report` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: report test docs venv clean

venv: $(STAMP)

$(STAMP): requirements.lock pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

report: $(STAMP)
	$(VENV)/bin/accel-jax report --out out/report

test: $(STAMP)
	$(PY) -m pytest -n 2 -q

# The documentation site (docs/ and the API reference from the docstrings), warnings as
# errors; its tools are pinned in requirements-docs.lock. CI runs it after the tests.
DOCS_STAMP := $(VENV)/.docs-installed

$(DOCS_STAMP): $(STAMP) requirements-docs.lock
	$(PY) -m pip install --quiet -r requirements-docs.lock
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	$(VENV)/bin/mkdocs build --strict --quiet

clean:
	rm -rf $(VENV) out
