# The two set-up commands of the README. Both work on a fresh machine:
# they create .venv, install the CPU torch wheel first (so no CUDA build is
# ever pulled in), then nefii with its extras at the versions of constraints.txt.
VENV ?= .venv
PY := $(VENV)/bin/python
TORCH_VERSION ?= 2.13.0
EXTRAS ?= dev,synth,colmap

.PHONY: demo test install clean mutants

$(VENV)/.installed: pyproject.toml constraints.txt Makefile
	@# Mitsuba's fast llvm variant (nefii synth) needs libLLVM >= 16; Debian 12's default 15 aborts.
	@# Best effort: without it nefii synth falls back to the (slower) scalar variant with a warning.
	@# Chromium runs the test of `nefii view` (the test skips itself without it).
	@missing=""; for p in libllvm19 chromium; do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ] && command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
		echo "installing$$missing (Debian packages)"; \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null) || \
		echo "could not install$$missing: nefii synth falls back to Mitsuba's scalar variant, the view test skips"; \
	fi
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "torch==$(TORCH_VERSION)"
	$(PY) -m pip install --quiet -c constraints.txt -e ".[$(EXTRAS)]"
	touch $@

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/nefii demo

test: install
	$(VENV)/bin/python -m pytest

clean:
	rm -rf $(VENV) build src/*.egg-info

# Mutation testing (slow, not run by CI): mutmut mutates src/nefii/render, fields, fit/losses.py, evaluate
# and io/checkpoints.py and runs the tests listed in pyproject.toml's [tool.mutmut] against each mutant.
# It works on a copy of the tree in build/mutmut. SCOPE=checkpoints|losses|metrics|table1|evaluate|fields|render
# narrows the copy's configuration to one scope (tests/mutmut_scope.py); MUTMUT_CHILDREN sets the workers.
# Results: `cd build/mutmut && ../../.venv/bin/mutmut results` (or `browse`). See docs/testing.md.
MUTMUT_VERSION ?= 3.8.1
SCOPE ?= all
MUTMUT_CHILDREN ?= 2
mutants: install
	$(PY) -m pip install --quiet "mutmut==$(MUTMUT_VERSION)"
	rm -rf build/mutmut && mkdir -p build/mutmut
	cp -r src tests pyproject.toml build/mutmut/
	$(PY) tests/mutmut_scope.py build/mutmut/pyproject.toml $(SCOPE)
	cd build/mutmut && OMP_NUM_THREADS=1 nice -n 19 $(abspath $(VENV))/bin/mutmut run --max-children $(MUTMUT_CHILDREN); \
		$(abspath $(VENV))/bin/mutmut results --all true > results.txt; \
		grep -c ": killed" results.txt | sed "s/^/killed: /"; grep -v ": killed" results.txt || true
