# `make run`: set up (a venv in .venv) and race BiFNet Table IV on the generated default data: every row on its
# published config (table.tuned_from=published), one planned look of 3 seeds per row (the cheapest paper table).
# `make test`: set up and run the tests.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup run test lint bench

$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	# torch first and pinned: the CPU wheel; a looser range could pull a multi-GB CUDA build.
	$(PY) -m pip install --quiet torch==2.13.0
	# the launchers', the tracking server's and the browser test's extras too: their tests are part of `make test`.
	# uv installs them in under a minute where pip takes three (the same versions; torch, installed, is kept), pip
	# where uv cannot be had. Compiled to bytecode at install, as pip does: where PYTHONDONTWRITEBYTECODE is set, an
	# uncompiled package is compiled again by every process that imports it (10 s more per job on the AVX2 EPYC).
	{ $(PY) -m pip install --quiet uv && $(VENV)/bin/uv pip install --quiet --compile-bytecode --python $(PY) -e ".[test,slurm,ray,server,browser]"; } \
		|| $(PY) -m pip install --quiet -e ".[test,slurm,ray,server,browser]"
	# the project's own modules too (an editable install is not compiled): every job process imports them, 0.2 s
	# each uncompiled on the AVX2 EPYC; a module edited later is compiled again where it is imported, as always
	$(PY) -m compileall -q ablate hydra_plugins
	touch $@

setup: $(VENV)/.installed

run: setup
	$(PY) -m ablate -m experiment=bifnet_table4 table.tuned_from=published 'scale.race.looks=[3]'

# the test files spread over every core, one file per worker at a time (module fixtures are built once; the Ray and
# PostgreSQL tests of one file never run beside each other), in the order tests/conftest.py gives them, slowest
# first: pytest-xdist would otherwise hand out the files with the most tests first and leave the slow ones for last
test: setup
	$(PY) -m pytest -q -n auto --dist loadfile --no-loadscope-reorder

# ruff (lint and format) on everything; mypy (every function annotated) on the package and the sweeper plugin
lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy ablate hydra_plugins

bench: setup
	for f in bench/bench_*.py; do echo "== $$f"; $(PY) $$f || exit 1; done
