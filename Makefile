# `make demo` and `make test` work on a fresh Debian machine with Python ≥ 3.10: they make
# .venv, install the package with all its extras, and the Debian libraries its wheels need
# (with Mesa's EGL/OSMesa when an off-screen render fails: tools/system-libs.sh checks one).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[all,test]'
	bash tools/system-libs.sh $(BIN)/python
	$(BIN)/reconstruct warm-up
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/reconstruct demo -o demo_output

# Two test processes: the suite's time budget (5 minutes) is set for a 2-core machine, and its
# slowest tests wait on subprocesses, browsers and clusters more than they compute.
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2

# The numbers in BENCHMARKS.md (the speed benchmark renders 48 photographs of 24 MP first).
bench: $(STAMP)
	$(BIN)/python benchmarks/accuracy.py
	$(BIN)/python benchmarks/decoders.py
	$(BIN)/python benchmarks/ptm_io.py
	$(BIN)/python benchmarks/speed.py
	$(BIN)/python benchmarks/speed.py --size 3000x2000
	$(BIN)/python benchmarks/robust_kernel.py
	$(BIN)/python benchmarks/batch.py
	$(BIN)/python benchmarks/normals_table.py
	$(BIN)/python benchmarks/relight_loo.py
	$(BIN)/python benchmarks/integration.py
	$(BIN)/python benchmarks/cg_solver.py
	$(BIN)/python benchmarks/decimation.py
	$(BIN)/python benchmarks/obj_export.py
	$(BIN)/python benchmarks/compare_speed.py
	$(BIN)/python benchmarks/nearlight.py
	$(BIN)/python benchmarks/calibration.py
	$(BIN)/python benchmarks/preview_relight.py
	$(BIN)/python benchmarks/report_html.py

clean:
	rm -rf $(VENV) demo_output .pytest_cache
