# appfusion: the README's commands. `make demo` and `make test` set up a fresh machine first (apt + .venv).
PY := .venv/bin/python
PYTEST_ARGS ?= -q -n 2 --timeout=600

.PHONY: setup demo test bench clean
setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) -m appfusion scan --demo --out out/demo

test: setup
	QT_QPA_PLATFORM=offscreen $(PY) -m pytest $(PYTEST_ARGS)

bench: setup
	$(PY) -m appfusion bench --quick --json out/bench.json

clean:
	rm -rf out .pytest_cache .hypothesis
