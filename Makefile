# The two commands users need: `make demo` and `make test`. Both set up first.
PY := .venv/bin/python
OUT ?= outputs

.PHONY: setup demo test lint bench clean

setup:
	@./.ci/setup.sh

demo: setup
	$(PY) -m pipeline.cli run configs/demo.yaml --out $(OUT)

test: setup
	$(PY) -m pytest -q -p no:cacheprovider tests

lint: setup
	$(PY) -m ruff check pipeline stages tests bench

bench: setup
	$(PY) bench/voxelise.py

clean:
	rm -rf $(OUT)/*/ .pytest_cache
