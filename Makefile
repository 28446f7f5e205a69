# Two entry points: `make demo` and `make test`. Both create .venv when it is missing, with the exact
# versions of uv.lock (`uv sync --locked`); uv itself (pinned) lives in .tools/.
#   make test                          core + dev tools
#   make install EXTRAS="dev lerobot"  choose the extras (dev torch gsplat xarm ray lerobot smolvla;
#                                      lerobot and smolvla need 3.12)
# The extras installed are remembered (in $(VENV)/.installed): when uv.lock or pyproject.toml change (a git
# pull), the next `make`, `make test` or `make demo` re-syncs with the same extras and says so.
#   make lock                          re-resolve uv.lock after editing a range in pyproject.toml
# VENV=.venv-py311 PYTHON=python3.11 makes a second environment beside the default one.
# Interpreter: python3.12 when one runs, else python3 (>= 3.11); choose another with PYTHON=/path/to/python.
ifndef PYTHON
PYTHON := $(shell for p in python3.12 $(wildcard $(HOME)/.pyenv/versions/3.12*/bin/python3.12) python3; do \
	"$$p" -c 'import sys; assert sys.version_info >= (3, 11); print(sys.executable)' 2>/dev/null && break; done)
endif
UV_VERSION := 0.13.8
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The extras of the last install (the stamp's words), else dev; EXTRAS=... on the command line wins.
# A stamp from before extras were remembered is empty: dev (+ lerobot when lerobot-eval is there), and
# that re-sync removes nothing (--inexact).
INSTALLED_EXTRAS := $(strip $(shell cat $(STAMP) 2>/dev/null))
LEGACY := $(and $(wildcard $(STAMP)),$(if $(INSTALLED_EXTRAS),,1))
EXTRAS ?= $(or $(INSTALLED_EXTRAS),dev $(if $(LEGACY),$(if $(wildcard $(VENV)/bin/lerobot-eval),lerobot)))
KEEP := $(if $(LEGACY),--inexact)
SYNC = $(UV) sync --locked --python $(PYTHON) $(addprefix --extra ,$(EXTRAS))
UV := .tools/bin/uv
# pytest-xdist processes for `make test` (whole test files to each); 0 runs the suite in one process
TEST_WORKERS ?= 2
# uv reads the system's CA bundle (as pip does) and never downloads an interpreter.
export UV_SYSTEM_CERTS := 1
export UV_PYTHON_DOWNLOADS := never
export UV_PROJECT_ENVIRONMENT := $(VENV)

.DEFAULT_GOAL := sync
.PHONY: sync demo test lint bench install lock clean

$(UV):
	@test -n "$(PYTHON)" || { echo "error: no python3.12 or python3 >= 3.11 found; run make PYTHON=/path/to/python3.12" >&2; exit 1; }
	$(PYTHON) -m venv .tools
	.tools/bin/python -m pip install --quiet uv==$(UV_VERSION)

$(STAMP): pyproject.toml uv.lock plugins/lerobot_env_twinbench/pyproject.toml | $(UV)
	@if [ -e $(STAMP) ]; then echo "note: uv.lock or pyproject.toml changed since $(VENV) was installed;" \
		"re-syncing it with the same extras: $(EXTRAS)$(if $(KEEP), (keeping every installed package))"; fi
	$(SYNC) $(KEEP)
	echo "$(EXTRAS)" > $(STAMP)

sync: $(STAMP)

install: | $(UV)
	$(SYNC)
	echo "$(EXTRAS)" > $(STAMP)

lock: | $(UV)
	$(UV) lock --python $(PYTHON)

demo: $(STAMP)
	$(PY) -m twinbench.cli demo

test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=15

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks plugins
	$(VENV)/bin/lint-imports

bench: $(STAMP)
	for f in benchmarks/*.py; do echo "== $$f"; $(PY) $$f; done

clean:
	rm -rf $(VENV) .tools outputs .pytest_cache
