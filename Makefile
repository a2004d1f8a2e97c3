# Quick start (README): `make demo` installs everything and runs the workflow on the demo
# capture; `make test` installs the test extras and runs the tests (.ci/run calls it).

PYTHON ?= python3
SUDO := $(shell [ "$$(id -u)" = "0" ] || echo sudo)

.PHONY: system install install-test demo test e2e e2e-workflow lint bench clean

system:  ## Open3D 0.20 needs the system library libusb-1.0
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || \
	  ($(SUDO) apt-get install -y -qq libusb-1.0-0 || \
	   ($(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0))

install: system
	$(PYTHON) -m pip install -q -e .

install-test: system
	$(PYTHON) -m pip install -q -e '.[test]'

demo: install  ## renders data/raw/demo if missing, then builds reports/demo/accuracy.pdf
	snakemake --cores 2

test: install-test
	$(PYTHON) -m pytest -n 2 --dist loadgroup --durations=15 -m "not e2e"

e2e-workflow: install-test  ## after the suite in CI: determinism, chunks, interruptions (whole runs)
	$(PYTHON) -m pytest -n 2 --durations=10 -m e2e tests/test_workflow.py

e2e: install-test  ## slower end-to-end check: three random rigs through the workflow
	$(PYTHON) -m pytest -m e2e tests/e2e  # one process: the workflow inside uses both cores

lint:
	ruff check .
	snakemake --lint

bench:
	$(PYTHON) benchmarks/run_all.py

clean:  ## stage outputs only; data/raw (captures) is kept
	rm -rf data/interim data/processed reports/* logs .snakemake
