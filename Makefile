# Two entry points: `make demo` and `make test`. Both create .venv when it is missing, with the exact
# versions of uv.lock (`uv sync --locked`); uv itself (pinned) lives in .tools/.
#   make test                          core + dev tools
#   make install EXTRAS="dev lerobot"  add extras (dev torch gsplat xarm ray lerobot; lerobot needs 3.12)
#   make lock                          re-resolve uv.lock after editing a range in pyproject.toml
# VENV=.venv-py311 PYTHON=python3.11 makes a second environment beside the default one.
# Interpreter: python3.12 when one runs, else python3 (>= 3.11); choose another with PYTHON=/path/to/python.
ifndef PYTHON
PYTHON := $(shell for p in python3.12 $(wildcard $(HOME)/.pyenv/versions/3.12*/bin/python3.12) python3; do \
	"$$p" -c 'import sys; assert sys.version_info >= (3, 11); print(sys.executable)' 2>/dev/null && break; done)
endif
UV_VERSION := 0.13.8
EXTRAS ?= dev
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
UV := .tools/bin/uv
# uv reads the system's CA bundle (as pip does) and never downloads an interpreter.
export UV_SYSTEM_CERTS := 1
export UV_PYTHON_DOWNLOADS := never
export UV_PROJECT_ENVIRONMENT := $(VENV)

.PHONY: demo test lint bench install lock clean

$(UV):
	@test -n "$(PYTHON)" || { echo "error: no python3.12 or python3 >= 3.11 found; run make PYTHON=/path/to/python3.12" >&2; exit 1; }
	$(PYTHON) -m venv .tools
	.tools/bin/python -m pip install --quiet uv==$(UV_VERSION)

$(STAMP): pyproject.toml uv.lock plugins/lerobot_env_twinbench/pyproject.toml | $(UV)
	$(UV) sync --locked --python $(PYTHON) $(addprefix --extra ,$(EXTRAS))
	touch $(STAMP)

install: | $(UV)
	$(UV) sync --locked --python $(PYTHON) $(addprefix --extra ,$(EXTRAS))
	touch $(STAMP)

lock: | $(UV)
	$(UV) lock --python $(PYTHON)

demo: $(STAMP)
	$(PY) -m twinbench.cli demo

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks plugins
	$(VENV)/bin/lint-imports

bench: $(STAMP)
	for f in benchmarks/*.py; do echo "== $$f"; $(PY) $$f; done

clean:
	rm -rf $(VENV) .tools outputs .pytest_cache
