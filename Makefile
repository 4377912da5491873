# Two commands for a fresh machine:  `make run`  and  `make test`  (see README.md).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup run serve demo test lint system-deps frontend-build

$(STAMP): pyproject.toml
	test -d $(VENV) || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q "torch==2.13.0"
	$(BIN)/pip install -q -e ".[dev]"
	touch $(STAMP)

frontend/node_modules/.installed: frontend/package.json frontend/package-lock.json
	cd frontend && npm ci --no-audit --no-fund
	touch $@

frontend-build: frontend/node_modules/.installed
	cd frontend && npm run build --if-present

setup: $(STAMP) frontend-build

# Tools the tests use from Debian: assimp (FBX), chromium (browser tests). Needs root; skipped when present.
system-deps:
	@(command -v assimp >/dev/null && test -x /usr/bin/chromium) || \
		(apt-get update -qq && apt-get install -y -qq assimp-utils chromium)

demo: setup
	mkdir -p out
	$(BIN)/retarget run retarget_core/data/samples/motions/007_03.bvh retarget_core/data/samples/characters/mh_male_bulky.glb \
		-o out/007_03_on_bulky.glb --before out/007_03_on_bulky_before.glb --metrics out/007_03_on_bulky_metrics.json

# The service on one machine: API + workers, SQLite and a server-less broker (REDIS_URL / DATABASE_URL to change).
serve: setup
	$(BIN)/python -m api.serve

run: demo serve

test: setup system-deps
	@redis-cli -h 127.0.0.1 -p 6379 ping >/dev/null 2>&1 || redis-server --daemonize yes --bind 127.0.0.1 --port 6379 --save "" --appendonly no
	$(BIN)/python -m pytest -q -ra

lint: setup
	$(BIN)/ruff check retarget_core api worker tests
	$(BIN)/mypy retarget_core api worker
