# packetrt: `make render` and `make test` do all set-up on a fresh machine.
VENV    ?= .venv
PYTHON  ?= python3
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed-stamp

# Scene search path: the shared scene folder beside the checkout, when it exists.
SHARED_SCENES := $(abspath ../shared/scenes)
ifeq ($(origin PACKETRT_SCENE_PATH), undefined)
  ifneq ($(wildcard $(SHARED_SCENES)),)
    export PACKETRT_SCENE_PATH := $(SHARED_SCENES)
  endif
endif

.PHONY: render test test-serial bench clean bytecode

$(STAMP): pyproject.toml .ci/system-deps
	bash .ci/system-deps
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,gpu,cluster,proximity]'
	touch $(STAMP)

# The project's own modules byte-compiled into their (git-ignored) __pycache__ folders, even where
# PYTHONDONTWRITEBYTECODE is set (it is on this project's hosts): an editable install compiles
# nothing, and without .pyc files every `packetrt` command compiles the engine's sources again
# (session 28: a warm `packetrt render` of the default scene 2.6-2.9 s without, 1.9-2.5 s with).
# Only stale files are compiled again.
PACKAGES := engine traversals frusta validation scenes

bytecode: $(STAMP)
	$(PY) -m compileall -q $(PACKAGES)

render: $(STAMP) bytecode
	$(VENV)/bin/packetrt render -o out/default.png --stats out/default.json

# One pytest worker per core (pytest-xdist), a test file per worker at a time so that its kernels
# compile once there: most of a cold run is numba compiling, one kernel at a time in a process,
# and two workers overlap it. The files go out longest first (tests/conftest.py's LONGEST_FIRST;
# --no-loadscope-reorder keeps that order). `make test-serial` is the same suite in one process.
# PYTHONDONTWRITEBYTECODE is emptied for the tests: pytest then keeps each test module's rewritten
# asserts in tests/__pycache__ instead of rewriting all of them in every worker (collection 9.7 ->
# 4.7 s a process, session 28), and the command-line children read the engine's .pyc files.
test: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -n auto --dist loadfile --no-loadscope-reorder

test-serial: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest

bench: $(STAMP)
	$(VENV)/bin/packetrt bench benchmarks/smoke.toml --out out/bench-smoke

# Any bundled matrix by name: `make bench-overbeck-packets` runs benchmarks/overbeck-packets.toml
# into out/bench-overbeck-packets/ and carries on an interrupted run.
bench-%: $(STAMP) benchmarks/%.toml
	$(VENV)/bin/packetrt bench benchmarks/$*.toml --out out/bench-$* --resume

clean:
	rm -rf $(VENV) out "$${XDG_CACHE_HOME:-$$HOME/.cache}/packetrt"
