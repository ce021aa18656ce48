# The two commands users need: `make demo` and `make test`. Both set up first.
PY := .venv/bin/python
OUT ?= outputs

.PHONY: setup demo test lint bench clean

setup:
	@./.ci/setup.sh

demo: setup
	$(PY) -m pipeline.cli run configs/demo.yaml --out $(OUT)

# Test files run in parallel worker processes (pytest-xdist; a file stays in one worker, so its
# module fixtures are built once): on 2 cores the suite takes 448 s instead of 668 s on a cold
# Numba cache (each worker compiles the kernels its files need) and 261 s instead of 375 s warm.
# At most 4 workers: each compiles on its own, and the kernels use every core already.
TEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 2); [ $$n -gt 4 ] && n=4; echo $$n)

test: setup
	$(PY) -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile tests

lint: setup
	$(PY) -m ruff check pipeline stages tests bench frepvdb

bench: setup bench-tools
	$(PY) bench/voxelise.py

# The anchors of bench/mesh.py and bench/voxelise.py: OpenVDB's vdb_tool (mesh2ls) from apt.
.PHONY: bench-tools
bench-tools:
	@command -v vdb_tool >/dev/null 2>&1 || { \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO="sudo"; \
	  echo "bench-tools: apt-get install -y libopenvdb-tools"; \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libopenvdb-tools; }

clean:
	rm -rf $(OUT)/*/ .pytest_cache

# Opens the exported files in ParaView, Blender and Chromium (tests/clients). Installs the
# programs with apt-get when missing (xvfb too: Debian's ParaView renders offscreen through X).
CLIENT_PROGRAMS := pvpython:paraview blender:blender chromium:chromium xvfb-run:xvfb
.PHONY: test-clients
test-clients: setup
	@missing=""; \
	for pair in $(CLIENT_PROGRAMS); do \
	  command -v "$${pair%%:*}" >/dev/null 2>&1 || missing="$$missing $${pair##*:}"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if ! command -v apt-get >/dev/null 2>&1; then \
	    echo "test-clients: SKIPPED: apt-get is not available to install$$missing; install them and rerun"; \
	    exit 0; \
	  fi; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO="sudo"; \
	  echo "test-clients: apt-get install -y$$missing"; \
	  $$SUDO apt-get update -qq || exit 1; \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing xauth || exit 1; \
	fi; \
	FREPVDB_CLIENTS=1 $(PY) -m pytest -q -p no:cacheprovider tests/clients
