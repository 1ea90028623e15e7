# Two commands do everything on a fresh machine: `make demo` and `make test`.
# Each creates or refreshes the local environment .venv first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: demo test lint bench synth results clean-venv

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

# docs/results.md from scratch: the accuracy sweep, the stability suite, the serial speed
# bench, the on-chip builds (from the recorded FPGA figures), then charts and tables
results: $(VENV)/.installed
	$(VENV)/bin/albcap bench accuracy --no-progress
	# (exits 1 when a method breaks an invariant; the violations go into the tables, so go on)
	-$(VENV)/bin/albcap bench regimes --no-progress
	$(VENV)/bin/albcap bench speed --out docs/figures/speed.json
	$(VENV)/bin/albcap bench builds --no-progress --out docs/figures/builds.json
	$(VENV)/bin/albcap chart --results docs/results.md docs/fpga.md

synth: $(VENV)/.installed
	$(VENV)/bin/albcap hdl synth

clean-venv:
	rm -rf $(VENV)
