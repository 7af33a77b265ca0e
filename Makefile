# relreward: one-command setup, run and test. Nothing needs to be exported beforehand:
# libtorch comes from the PyTorch wheel in .venv (see .cargo/config.toml), protoc from a
# vendored crate, SQLite is compiled in, and binaries carry an rpath to libtorch.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

PYTHON ?= python3
VENV := .venv
REQUIREMENTS := tests/python/requirements.txt
SETUP_STAMP := $(VENV)/.relreward-setup
# The relreward Python package (client/python), installed into .venv; reinstalled when its
# sources or the protos it compiles change.
PY_CLIENT_STAMP := $(VENV)/.relreward-python-client
PY_CLIENT_SOURCES := client/python/pyproject.toml client/python/setup.py client/python/MANIFEST.in \
	$(wildcard client/python/src/relreward/*.py client/python/src/relreward/v1/__init__.py proto/relreward/v1/*.proto)
# The development package (dev/python: relreward_dev, the server launcher and the PyTorch
# reference nets that tests, experiments and benchmarks import), installed into .venv the same
# way; built from a copy in a temporary directory so that no build/ is left in the checkout.
PY_DEV_STAMP := $(VENV)/.relreward-dev
PY_DEV_SOURCES := dev/python/pyproject.toml $(wildcard dev/python/src/relreward_dev/*.py)
CARGO := cargo
CARGO_PROFILE := --release
BIN := target/release
# Arguments for `make run`, e.g. make run ARGS="--listen 127.0.0.1:6000 --data-dir /tmp/rr".
ARGS ?=

.PHONY: help setup build run test test-cluster lint fmt clean demo bench soak steer images images-safe rl-pointmaze rl-offline
# Arguments for `make demo`, e.g. make demo DEMO_ARGS="--layout medium --goals 4".
DEMO_ARGS ?=

help:
	@echo "make run    set everything up, build, and start relreward-server on 127.0.0.1:50051"
	@echo "make test   set everything up and run every test (and validate deploy/)"
	@echo "make test-cluster  PostgreSQL + S3 server + 2 serving replicas + 2 workers on loopback"
	@echo "make demo   the Maze2D pipeline end to end (starts a server if none answers)"
	@echo "make bench  relreward against the PyTorch references: serving, training, sampling; 1 vs 2 replicas (writes BENCHMARKS.md)"
	@echo "make soak   the 10-minute load and soak test (tests/soak.sh; make test runs 60 s of it)"
	@echo "make steer  locomotion steering experiment, ENV=hopper|halfcheetah|walker2d (paper section 5.2)"
	@echo "make images the digits experiment: Algorithm 2 on two image DDPMs (experiments/images/digits.py)"
	@echo "make images-safe one conditional latent DDPM, two samplers (plain and safety-guided), Algorithm 2 (experiments/images/safe_latent.py)"
	@echo "make rl-pointmaze  SAC agents on the extracted reward alone in MuJoCo PointMaze (issue 35; RL_ARGS)"
	@echo "make rl-offline    IQL (d3rlpy) on relabelled locomotion data, OFFLINE_ENV=halfcheetah (issue 35)"
	@echo "make lint   rustfmt check and clippy"
	@echo "make clean  remove build outputs (keeps .venv and data/)"

## setup: the Python venv carrying libtorch (PyTorch 2.13.0), the test scripts' packages,
## the relreward Python package (client/python; its stubs are compiled from proto/ as it builds)
## and the development package (dev/python).
setup: $(SETUP_STAMP) $(PY_CLIENT_STAMP) $(PY_DEV_STAMP)

$(SETUP_STAMP): $(REQUIREMENTS)
	@command -v $(CARGO) >/dev/null || { echo "cargo not found: install the Rust toolchain (rustup)"; exit 1; }
	@test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	@# The venv takes about 6 GB and a release target/ about 5 GB. Say so before pip runs out of
	@# room half-way (its error names neither).
	@free_kb=$$(df -Pk . | awk 'NR == 2 { print $$4 }'); \
	  if [[ $$free_kb -lt $$((12 * 1024 * 1024)) ]]; then \
	    echo "warning: $$((free_kb / 1024 / 1024)) GB free here; .venv needs about 6 GB and target/ about 5 GB"; fi
	@# --no-cache-dir: a second copy of the 3 GB of wheels in ~/.cache would only raise the peak.
	$(VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-cache-dir -r $(REQUIREMENTS)
	@# A version-independent path to the torch package, used as LIBTORCH by .cargo/config.toml.
	ln -sfn "$$($(VENV)/bin/python -c 'import os, torch; print(os.path.dirname(torch.__file__))')" $(VENV)/torch-root
	@touch $@

$(PY_CLIENT_STAMP): $(SETUP_STAMP) $(PY_CLIENT_SOURCES)
	$(VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-cache-dir --no-build-isolation --no-deps \
	  --force-reinstall ./client/python
	@touch $@

$(PY_DEV_STAMP): $(SETUP_STAMP) $(PY_DEV_SOURCES)
	@tmp=$$(mktemp -d); trap 'rm -rf "$$tmp"' EXIT; \
	  cp -R dev/python/pyproject.toml dev/python/src "$$tmp"/; \
	  $(VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-cache-dir --no-build-isolation \
	    --no-deps --force-reinstall "$$tmp"
	@touch $@

build: setup
	$(CARGO) build $(CARGO_PROFILE) --workspace --bins

run: build
	$(BIN)/relreward-server $(ARGS)

## test: every test. The end-to-end crate spawns target/release/relreward-server, built above.
## Then the Python package's tests (client/python/tests, pytest, against the same binaries),
## then the container image and manifests are checked (hadolint, kubernetes-validate, yamllint).
test: build
	$(CARGO) test $(CARGO_PROFILE) --workspace --no-fail-fast
	$(VENV)/bin/python -m pytest client/python/tests -q
	deploy/validate.sh

## images: the paper's section 5.3 on scikit-learn's 8x8 digits (experiments/images/digits.py):
## two native UNet2D DDPMs, Algorithm 2 from the models only, Algorithm 1, the discriminator,
## separation, pictures and steering; writes docs/images/digits/. IMAGES_ARGS e.g. "--seed 1".
IMAGES_ARGS ?=
images: build
	$(VENV)/bin/python experiments/images/digits.py $(IMAGES_ARGS)

## images-safe: the paper's section 5.3 as the paper ran it (experiments/images/safe_latent.py):
## one class-conditional latent DDPM on the digits' autoencoder latents, base = classifier-free
## guidance, expert = the same plus Safe Latent Diffusion's guidance away from the unsafe classes,
## Algorithm 2 from the two samplers; writes docs/images/safe_latent/. SAFE_ARGS e.g. "--seed 1".
images-safe: build
	$(VENV)/bin/python experiments/images/safe_latent.py $(SAFE_ARGS)

## test-cluster: the shared backend across processes (tests/cluster/run.sh): a real PostgreSQL
## (Debian package, installed if missing) and s3s-fs (built into .tools/ once), two serving
## replicas and two workers; see tests/tests/cluster.rs.
test-cluster: build
	tests/cluster/run.sh

## demo: uses the server at RELREWARD_ENDPOINT (default 127.0.0.1:50051) if it answers,
## otherwise starts one on that port with its data under demo-out/ and stops it afterwards.
demo: build
	@if $(BIN)/relreward health >/dev/null 2>&1; then \
	  $(BIN)/relreward demo $(DEMO_ARGS); \
	else \
	  mkdir -p demo-out; \
	  RELREWARD__METRICS__LISTEN= $(BIN)/relreward-server --data-dir demo-out/server-data >demo-out/server.out 2>demo-out/server.log & \
	  server=$$!; trap 'kill $$server 2>/dev/null || true' EXIT; \
	  for _ in $$(seq 300); do $(BIN)/relreward health >/dev/null 2>&1 && break; sleep 0.1; done; \
	  $(BIN)/relreward demo $(DEMO_ARGS); \
	fi

## bench: each script runs relreward and its reference alternately and splices its own section
## of BENCHMARKS.md (tests/bench/splice.py); about 20 minutes on a 2-core machine.
bench: build
	tests/bench/serving.sh
	tests/bench/training.sh
	tests/bench/cluster.sh
	tests/bench/amortised.sh
	tests/bench/oip_http.sh

## soak: concurrent Score, GradientStream, Sample, uploads and a training job for SOAK_SECS
## (default 600) against one loopback server; see docs/reliability.md.
soak: build
	tests/soak.sh

## steer: closed-loop steering of a locomotion planner (paper section 5.2) in ENV (hopper,
## halfcheetah, walker2d) from the committed ARS policy and planners under experiments/locomotion:
## the data sets by deterministic rollouts, then the reward, the discriminator and every arm
## (experiments/locomotion/steer.py; STEER_ARGS adds its flags, e.g. --full). Writes steer-out/.
## Defaults: the reward's loss weighted on the executed action (10) and not on the inpainted
## state (0); each guided arm sweeps both guidance rules (posterior mean, x_t) and omega over
## {0.3, 1, 3} at t_stopgrad 0, then t_stopgrad 2 at the best, three episodes per setting on
## seeds 10000..10002 (never a reported seed); 5 episodes per arm on seeds 0..4.
## Results: docs/results.md ("Locomotion steering").
ENV ?= hopper
STEER_ARGS ?=
steer: build
	$(VENV)/bin/python experiments/locomotion/data.py --env $(ENV) --out steer-out/data
	$(VENV)/bin/python experiments/locomotion/steer.py --env $(ENV) --data steer-out/data --work steer-out/$(ENV) \
	  $(STEER_ARGS)

## rl-pointmaze: agents trained on the extracted reward alone (issue 35 item 3): SAC in MuJoCo
## PointMaze umaze per goal (default the four of docs/results.md): generate.py data, one
## `relreward extract --discriminator`, then the arms rho, discriminator (logit), env (ceiling),
## constant (floor), 2 seeds each, 20 evaluation episodes per agent on reserved seeds
## (experiments/pointmaze/rl.py; RL_ARGS adds its flags, e.g. RL_ARGS="--goals 3,1 --seeds 3").
## Writes rl-pointmaze-out/ (results.md, results.json, curves.png). Method: docs/pointmaze_rl.md.
RL_ARGS ?=
rl-pointmaze: build
	$(VENV)/bin/python experiments/pointmaze/rl.py --work rl-pointmaze-out $(RL_ARGS)

## rl-offline: offline RL on relabelled data (issue 35 item 4; docs/offline_rl.md): OFFLINE_ENV's
## medium-replay set relabelled by the steering experiment's reward and discriminator, d3rlpy IQL
## on four arms (true, rho, discriminator, constant), 2 seeds x 10 episodes. Writes offline-out/.
## OFFLINE_ARGS adds flags (e.g. --paper-scale, --steps N).
OFFLINE_ENV ?= halfcheetah
OFFLINE_ARGS ?=
rl-offline: build
	$(VENV)/bin/python experiments/locomotion/data.py --env $(OFFLINE_ENV) --out offline-out/data
	$(VENV)/bin/python experiments/locomotion/offline.py --env $(OFFLINE_ENV) --data offline-out/data \
	  --work offline-out/$(OFFLINE_ENV) $(OFFLINE_ARGS)

lint: setup
	$(CARGO) fmt --all -- --check
	$(CARGO) clippy $(CARGO_PROFILE) --workspace --all-targets -- -D warnings
	deploy/validate.sh

fmt:
	$(CARGO) fmt --all

clean:
	$(CARGO) clean
