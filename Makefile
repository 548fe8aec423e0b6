# The two set-up commands of the README. Both work on a fresh machine:
# they create .venv, install the CPU torch wheel first (so no CUDA build is
# ever pulled in), then nefii with its extras.
VENV ?= .venv
PY := $(VENV)/bin/python
TORCH_VERSION ?= 2.13.0
EXTRAS ?= dev,synth,colmap

.PHONY: demo test install clean

$(VENV)/.installed: pyproject.toml Makefile
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "torch==$(TORCH_VERSION)"
	$(PY) -m pip install --quiet -e ".[$(EXTRAS)]"
	touch $@

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/nefii demo

test: install
	$(VENV)/bin/python -m pytest

clean:
	rm -rf $(VENV) build src/*.egg-info
