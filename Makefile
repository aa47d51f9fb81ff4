# The README's commands live here so they stay in one place.
# `make repro`: set up and run the default pipeline. `make test`: set up and run the test suite (what CI runs).

PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Stage commands call `python`, `dvc`; the venv must come first on PATH.
export PATH := $(CURDIR)/$(BIN):$(PATH)

.PHONY: setup render-deps repro dry dry-exp test test-fast lint docs benchmark ui sweep study exps tracking-server tracking-server-stop \
	object-store object-store-stop dvc-remote

# A start-up hook that older versions of this Makefile copied into the venv is removed, so nothing but the pinned
# packages runs at interpreter start.
setup: $(STAMP)
	@rm -f "$$($(BIN)/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/carp-dvc-dry-run.pth"

$(STAMP): requirements.lock requirements-binaries.lock pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.lock
	$(BIN)/python -m pip install --quiet --require-hashes --no-deps -r requirements-binaries.lock
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $(STAMP)

# Headless offscreen rendering (camera observations, evaluation videos) through EGL with Mesa: installs the Debian
# packages that are missing (needs root); does nothing when all are present.
RENDER_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri
render-deps:
	@missing="$$(for package in $(RENDER_PACKAGES); do dpkg -s $$package > /dev/null 2>&1 || echo $$package; done)"; \
	if [ -n "$$missing" ]; then \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing; \
	fi

repro: setup
	dvc repro

# What `dvc repro` (or `dvc exp run $(ARGS)`) would run, also on a fresh clone before any stage has (tools/dvc_dry.py).
dry: setup
	$(BIN)/python tools/dvc_dry.py repro $(ARGS)

dry-exp: setup
	$(BIN)/python tools/dvc_dry.py exp run $(ARGS)

# Tests run in TEST_WORKERS pytest-xdist processes (one per core of a 2-core CPU); a module's tests stay in one
# process, so its module-scoped fixtures are built once. Modules are handed out in the order tests/conftest.py gives
# them (the long end-to-end ones first, so that the short ones even out the workers' ends), not xdist's default
# order by number of tests. `make test TEST_WORKERS=0` runs them in this process.
TEST_WORKERS ?= 2
PYTEST := $(BIN)/python -m pytest $(if $(filter-out 0,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadscope --no-loadscope-reorder)

test: setup
	$(PYTEST)

test-fast: setup
	$(PYTEST) -m "not slow"

# Style, then the two documentation checks (also run by `make test` as tests): no development-history words in the
# user-facing files, and docs/params.md documents every param and is what `make docs` generates.
lint: setup
	$(BIN)/ruff check src pipeline tests benchmarks tools examples
	$(BIN)/ruff format --check src pipeline tests benchmarks tools examples
	$(BIN)/python tools/check_history_words.py
	$(BIN)/python tools/params_docs.py --check

# docs/params.md from the docstrings of src/carp/config.py.
docs: setup
	$(BIN)/python tools/params_docs.py

benchmark: setup
	$(BIN)/python benchmarks/tokenizer_throughput.py
	$(BIN)/python benchmarks/policy_speed.py
	$(BIN)/python benchmarks/policy_families.py
	$(BIN)/python benchmarks/rendering_cost.py
	$(BIN)/python benchmarks/image_windows.py
	$(BIN)/python benchmarks/serving_latency.py

ui: setup
	$(BIN)/mlflow ui --backend-store-uri sqlite:///$(CURDIR)/mlflow.db --port 5000

# Optuna sweep over scales and codebook size (README "Experiments and sweeps"); `make sweep TRIALS=4` sets the budget.
sweep: setup
	$(BIN)/python pipeline/sweep.py $(if $(TRIALS),--trials $(TRIALS))

# The paper's studies as DVC experiments in this workspace (README "Comparisons"): `make study STUDY=data_efficiency`.
STUDY ?= data_efficiency
study: setup
	$(BIN)/python pipeline/study.py $(STUDY)

# Experiments side by side: state (a failed queued experiment shows Failed, and its metrics are not its own), swept
# params, success rate, tokenizer reconstruction error, latency per chunk.
EXP_COLUMNS := ^(Experiment|State|scales|codebook_size|success_rate|rmse_percent_range/mean|latency_(predict|decode)_ms_median)$$
exps: setup
	$(BIN)/dvc exp show --drop '.*' --keep '$(EXP_COLUMNS)'

# Running on several machines (README). A shared MLflow tracking server on PostgreSQL, everything kept in DIR:
# `make tracking-server DIR=/srv/carp-tracking [PORT=5000] [HOST=0.0.0.0] [ALLOWED_HOSTS=tracking.lab]
# [ARTIFACTS=s3://bucket/mlflow]`, then the param `tracking.uri: http://<host>:<port>`. Re-running it restarts
# whatever is down; `make tracking-server-stop DIR=...`.
tracking-server: setup
	$(BIN)/python tools/tracking_server.py start --dir "$(DIR)" $(if $(PORT),--port $(PORT)) \
		$(if $(HOST),--host $(HOST)) $(if $(ALLOWED_HOSTS),--allowed-hosts $(ALLOWED_HOSTS)) \
		$(if $(ARTIFACTS),--artifacts-destination $(ARTIFACTS))

tracking-server-stop: setup
	$(BIN)/python tools/tracking_server.py stop --dir "$(DIR)"

# An S3-compatible object store (SeaweedFS) for a lab without one: `make object-store DIR=/srv/carp-s3 [PORT=8333]
# [HOST=0.0.0.0]`; `tools/object_store.py env --dir DIR` prints its client settings.
object-store: setup
	$(BIN)/python tools/object_store.py start --dir "$(DIR)" $(if $(PORT),--port $(PORT)) $(if $(HOST),--host $(HOST))

object-store-stop: setup
	$(BIN)/python tools/object_store.py stop --dir "$(DIR)"

# The default DVC remote: `make dvc-remote URL=/mnt/share/carp-dvc` or `make dvc-remote URL=s3://bucket/carp
# [ENDPOINT=http://storage:8333]`; commit .dvc/config, then `dvc push` / `dvc pull`.
dvc-remote: setup
	$(BIN)/python tools/dvc_remote.py "$(URL)" $(if $(ENDPOINT),--endpoint-url $(ENDPOINT))
