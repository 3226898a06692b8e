PY := .venv/bin/python
VENV_STAMP := .venv/.installed

.PHONY: run test test-all bench network clean

$(VENV_STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -e '.[test]'
	touch $(VENV_STAMP)

run: $(VENV_STAMP)
	bash scripts/run_local.sh

# every test but the slow scenarios and studies, on two processes (one module each at a time)
test: $(VENV_STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not slow" tests

# every test, one process: what CI runs
test-all: $(VENV_STAMP)
	$(PY) -m pytest -q tests

bench: $(VENV_STAMP)
	.venv/bin/heartctl bench solver

network: $(VENV_STAMP)
	bash scripts/build_network.sh

clean:
	rm -rf .venv out runs *.egg-info
