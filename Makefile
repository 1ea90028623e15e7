# Two commands do everything on a fresh machine: `make demo` and `make test`.
# Each creates or refreshes the local environment .venv first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: demo test lint bench synth clean-venv

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $@

demo: $(VENV)/.installed
	$(VENV)/bin/albcap demo
	$(VENV)/bin/albcap survey

test: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q -n 2

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .

bench: $(VENV)/.installed
	$(VENV)/bin/albcap bench model --json

synth: $(VENV)/.installed
	$(VENV)/bin/albcap hdl synth

clean-venv:
	rm -rf $(VENV)
