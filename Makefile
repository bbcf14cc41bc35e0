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

.PHONY: render test test-parallel bench clean

$(STAMP): pyproject.toml .ci/system-deps
	bash .ci/system-deps
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,gpu,cluster]'
	touch $(STAMP)

render: $(STAMP)
	$(VENV)/bin/packetrt render -o out/default.png --stats out/default.json

test: $(STAMP)
	$(PY) -m pytest

# The same suite in one pytest worker per core, a test file per worker at a time (its kernels
# compile once there): a cold numba cache compiles on every core at once. See the README.
test-parallel: $(STAMP)
	$(PY) -m pytest -n auto --dist loadfile

bench: $(STAMP)
	$(VENV)/bin/packetrt bench benchmarks/smoke.toml --out out/bench-smoke

# Any bundled matrix by name: `make bench-overbeck-packets` runs benchmarks/overbeck-packets.toml
# into out/bench-overbeck-packets/ and carries on an interrupted run.
bench-%: $(STAMP) benchmarks/%.toml
	$(VENV)/bin/packetrt bench benchmarks/$*.toml --out out/bench-$* --resume

clean:
	rm -rf $(VENV) out "$${XDG_CACHE_HOME:-$$HOME/.cache}/packetrt"
