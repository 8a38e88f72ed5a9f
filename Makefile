# Two entry points: `make report` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: report test docs typecheck venv clean

venv: $(STAMP)

$(STAMP): requirements.lock pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

report: $(STAMP)
	$(VENV)/bin/accel-jax report --out out/report

# --durations: the slowest tests' times at the end of every run (CI's log), so that where the
# suite's time goes is seen without a separate profiling run.
test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadgroup -q --durations=25

# The project's own checks (not needed to use the package), their tools pinned in
# requirements-dev.lock; CI runs both after the tests. `docs`: the documentation site
# (docs/, the API reference from the docstrings, and notebooks/*.py executed by the build in
# a Jupyter kernel from a temporary folder, figures included: mkdocs-jupyter and
# mkdocs_hooks.py, about a minute) with warnings as errors. `typecheck`: pyright in its
# standard mode on accel_jax/ ([tool.pyright] in pyproject.toml).
DEV_STAMP := $(VENV)/.dev-installed

$(DEV_STAMP): $(STAMP) requirements-dev.lock
	$(PY) -m pip install --quiet -r requirements-dev.lock
	touch $(DEV_STAMP)

docs: $(DEV_STAMP)
	$(VENV)/bin/mkdocs build --strict --quiet

typecheck: $(DEV_STAMP)
	$(PY) -m pyright --project . --stats

clean:
	rm -rf $(VENV) out
