# Two commands on a fresh machine:
#   make demo   — create .venv, install jaxsh, run the end-to-end synthetic pipeline
#   make test   — create .venv, install jaxsh with its test extras, run the test suite
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
PYTEST_ARGS ?=

.PHONY: demo test test-all bench install install-tests clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

install: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .

install-tests: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[tests]"

demo: install
	$(BIN)/jaxsh demo --out demo_out --json demo_out/report.json

# The CI suite: everything but tests marked slow; notebooks run small. Files are kept on one worker each
# (--dist loadfile), so a module's fixtures and compiled programs are built once, not once per worker.
# The tests are compiled at XLA's backend optimization level 0 (TEST_XLA_FLAGS): compilation is most of
# their time, and level 0 cut the suite by 30 % (docs/performance.md, "Thirtieth round"). The notebooks,
# end to end, run as a user's programs are compiled (XLA's default), and so does `make test-all`;
# `make test TEST_XLA_FLAGS=` compiles the tests at the default as well. (XLA reads a value that does not
# start with "--" as a file name and aborts: the `echo` leaves no leading space.)
TEST_XLA_FLAGS ?= --xla_backend_optimization_level=0

test: install-tests
	XLA_FLAGS="$$(echo $(TEST_XLA_FLAGS) $${XLA_FLAGS:-})" $(BIN)/python -m pytest -m "not slow" -n 2 --dist loadfile $(PYTEST_ARGS) tests
	JAXSH_NOTEBOOK_SMALL=1 $(BIN)/python -m pytest -n 2 --dist loadfile --nbmake notebooks

test-all: install-tests
	$(BIN)/python -m pytest -n 2 --dist loadfile --nbmake tests notebooks

bench: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[benchmarks]"
	$(BIN)/python benchmarks/bench_sh.py
	$(BIN)/python benchmarks/bench_sh.py --only basis --hugepages
	$(BIN)/python benchmarks/bench_convolution.py
	$(BIN)/python benchmarks/bench_render.py
	$(BIN)/python benchmarks/bench_render_table.py
	$(BIN)/python benchmarks/bench_mitsuba.py
	$(BIN)/python benchmarks/bench_sharing.py
	$(BIN)/python benchmarks/bench_inverse.py
	$(BIN)/python benchmarks/bench_capture.py
	$(BIN)/python benchmarks/bench_scale.py
	$(BIN)/python benchmarks/bench_gpu.py
	$(BIN)/python benchmarks/bench_cold.py

clean:
	rm -rf $(VENV) demo_out .pytest_cache .hypothesis
