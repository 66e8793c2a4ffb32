# embedrl developer tasks. `make demo` and `make test` work on a fresh machine.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: help setup deps apt-packages demo test test-fast lint type format bench bench-target export-example targets-example policies clean

setup: $(STAMP) ## the virtual environment .venv with embedrl and its Python dependencies

# Debian packages the tests need: cross compiler, newlib, QEMU (Cortex-M); can-utils (its cangen floods the
# bus in the fault catalogue); clang (libFuzzer: make -C runtime_c fuzz); clang-19 and llvm-19 (coverage with
# MC/DC: make -C runtime_c coverage, the report's coverage check); and what each CAN sandbox provider needs
# where the kernel has no CAN (hil/sandbox: its PROVIDERS say, e.g. User-Mode Linux, kmod, iproute2,
# patchelf for uml; QEMU, busybox and Debian's stable kernel with its vcan module for qemu). Installed when
# missing (as root or with passwordless sudo); otherwise the command to run is printed. Then a User-Mode
# Linux >= 7.2 is cached for CPUs on which Debian stable's UML dies (python -m embedrl.hil.sandbox.provision;
# no network once cached).
APT_PACKAGES := gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm can-utils clang clang-19 llvm-19 \
    cppcheck chromium
SANDBOX_PACKAGES = $(PY) -c 'from embedrl.hil.sandbox import debian_packages; print(*debian_packages())'
deps: apt-packages $(STAMP) ## setup, the Debian packages and the cached User-Mode Linux the tests need
	$(PY) -m embedrl.hil.sandbox.provision

apt-packages: $(STAMP) ## install the missing Debian packages (as root or with passwordless sudo)
	@sandbox=$$($(SANDBOX_PACKAGES)) || exit 1; \
	missing=""; for p in $(APT_PACKAGES) $$sandbox; do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	echo "installing Debian packages:$$missing"; \
	if [ "$$(id -u)" = 0 ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO=sudo; \
	else echo "missing Debian packages:$$missing; run: sudo apt-get install$$missing" >&2; exit 1; fi; \
	$$SUDO apt-get update -q && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q $$missing

# torch first and pinned: an unpinned torch pulls several GB of CUDA wheels.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# The main job, the whole chain: the potential-field baseline; the shipped TD3 policy
# (policies/static/td3.zip; the example actor imitating the baseline if it is missing); export -> ONNX
# -> C, verified, and Cortex-M4 firmware on QEMU; the C policy as a CAN node driven by the simulator over
# vcan (User-Mode Linux where the kernel has no CAN), then the same node as Cortex-M4 firmware on QEMU in
# the loop; the int8 and q15 exports; the deployment report (report.html) and the plots in $(OUT)/demo.
DEMO_POLICY ?= $(firstword $(wildcard policies/static/td3.zip) $(OUT)/example/td3.zip)
demo: deps $(STAMP) ## the whole chain: baseline, export, HIL (host and firmware node), report, in $(OUT)/demo
	$(VENV)/bin/embedrl eval --controller potential-field --episodes 20 --seed 0 \
	    --json $(OUT)/demo/eval.json --plot $(OUT)/demo/trajectories.png
	$(VENV)/bin/embedrl render --controller potential-field --seed 0 --out $(OUT)/demo/episode.gif
	test -f $(DEMO_POLICY) || $(PY) -m embedrl.export.example $(DEMO_POLICY)
	$(VENV)/bin/embedrl export $(DEMO_POLICY) --out $(OUT)/demo/export --force --target cortex-m4
	for q in int8 q15; do \
	    $(VENV)/bin/embedrl export $(DEMO_POLICY) --out $(OUT)/demo/export-$$q --force --quantize $$q --episodes 0 \
	        || exit 1; \
	done
	$(VENV)/bin/embedrl hil run --export-dir $(OUT)/demo/export --episodes 20 --seed 0 --coverage \
	    --json $(OUT)/demo/hil.json --log $(OUT)/demo/frames.log --plot $(OUT)/demo
	$(VENV)/bin/embedrl hil run --export-dir $(OUT)/demo/export --episodes 3 --seed 0 --node firmware \
	    --target cortex-m4 --json $(OUT)/demo/hil-firmware.json
	$(VENV)/bin/embedrl verify-chain $(OUT)/demo/export
	$(VENV)/bin/embedrl report $(OUT)/demo/export --hil $(OUT)/demo/hil.json --hil $(OUT)/demo/hil-firmware.json \
	    --also $(OUT)/demo/export-int8 --also $(OUT)/demo/export-q15 --out $(OUT)/demo/report.html
	@echo "demo: wrote $(OUT)/demo (eval.json, trajectories.png, episode.gif, export/, export-int8/, export-q15/, \
	hil.json, hil.coverage/, hil-firmware.json, frames.log, hil_*.png, report.html)"

# How the shipped policies were made, each shipped only if it succeeds in >= 95% of 200 episodes on seeds
# training never used (train/ship.py). policies/static/{ddpg,td3,sac,ppo}.zip were trained past the stop
# criterion to the budget and shipped as trained last (before runs kept their best validated checkpoint: a
# re-run ships that one); policies/{moving-shelf,two-robots}/td3.zip are their runs' best validated checkpoints.
policies: $(STAMP) ## train the shipped policies again (hours), each shipped only if it passes its test
	for a in ddpg td3 sac; do \
	    $(VENV)/bin/embedrl train --algo $$a --preset tuned --seed 1 --out $(OUT)/ship/$$a --max-steps 100000 \
	        --keep-training && $(PY) -m embedrl.train.ship $(OUT)/ship/$$a $$a || exit 1; \
	done
	$(VENV)/bin/embedrl train --algo ppo --preset tuned --seed 1 --out $(OUT)/ship/ppo --max-steps 60000 \
	    --keep-training && $(PY) -m embedrl.train.ship $(OUT)/ship/ppo ppo
	for s in moving-shelf two-robots; do \
	    $(VENV)/bin/embedrl train --scenario $$s --algo td3 --preset tuned --seed 1 --out $(OUT)/ship/$$s-td3 \
	        --max-steps 300000 && $(PY) -m embedrl.train.ship $(OUT)/ship/$$s-td3 td3 || exit 1; \
	done

# The suite in tiers (markers in pyproject.toml, set by the fixtures a test uses: tests/conftest.py). pytest is
# exec'd, so that make's SIGTERM (timeout, CI cancelling) reaches it and the session stops, guests closed.
# Both run on TEST_WORKERS pytest-xdist workers, a test file per worker at a time (tests/conftest.py).
TEST_WORKERS ?= 2
SIDE_BY_SIDE = -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder
FAST_TIER := not slow and not sandbox and not qemu and not training
test: deps $(STAMP) ## the whole test suite, then its 25 slowest tests
	exec $(PY) -m pytest $(SIDE_BY_SIDE) --durations=25

test-fast: $(STAMP) ## the tests that are not slow, boot no sandbox, run no QEMU and train nothing (minutes)
	exec $(PY) -m pytest $(SIDE_BY_SIDE) -m "$(FAST_TIER)"

lint: $(STAMP) ## ruff check and ruff format --check
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

type: $(STAMP) ## mypy over every file (tests/typecheck.py)
	$(PY) -m tests.typecheck

format: $(STAMP) ## ruff format and ruff check --fix
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

# Peer code generators for the benchmarks (host and Cortex-M), in their own environment under tools/ (never a
# dependency of embedrl): emx-onnx-cgen, pinned.
EMX := tools/emx/bin/emx-onnx-cgen
$(EMX):
	$(PYTHON) -m venv tools/emx
	tools/emx/bin/pip install --quiet emx-onnx-cgen==1.4.0

# How long make bench measures: env steps, HIL lock-step episodes and floor exchanges (smaller: quicker, noisier).
BENCH_ENV_STEPS ?= 50000
BENCH_HIL_EPISODES ?= 60
BENCH_HIL_EXCHANGES ?= 6000
# Closed-loop episodes each export of the example verifies (make export-example, make targets-example).
EXAMPLE_EPISODES ?= 200
bench: deps $(STAMP) $(EMX) ## env, export and HIL benchmarks, JSON in $(OUT)/bench
	$(VENV)/bin/embedrl bench-env --steps $(BENCH_ENV_STEPS) --json $(OUT)/bench/env.json
	$(VENV)/bin/embedrl bench-export --emx $(EMX) --json $(OUT)/bench/export.json
	$(VENV)/bin/embedrl export policies/static/td3.zip --out $(OUT)/bench/td3-float32 --force --episodes 0
	for q in int8 int8-weights q15; do \
	    $(VENV)/bin/embedrl export policies/static/td3.zip --out $(OUT)/bench/td3-$$q --force --episodes 0 \
	        --quantize $$q && $(VENV)/bin/embedrl bench-export --export-dir $(OUT)/bench/td3-$$q \
	        --float32-dir $(OUT)/bench/td3-float32 --json $(OUT)/bench/export-$$q.json || exit 1; \
	done
	$(VENV)/bin/embedrl hil bench --export-dir $(OUT)/bench/td3-float32 --episodes $(BENCH_HIL_EPISODES) \
	    --exchanges $(BENCH_HIL_EXCHANGES) --json $(OUT)/bench/hil.json

# Instructions, estimated cycles and cycles per multiply-add per inference on the Cortex-M cores: embedrl's C
# of the shipped policy in every precision, its float32 beside emx-onnx-cgen's C of the same ONNX, on QEMU.
bench-target: $(STAMP) $(EMX) ## cycles per inference and per multiply-add on Cortex-M, every precision, beside emx-onnx-cgen
	$(VENV)/bin/embedrl export policies/static/td3.zip --out $(OUT)/bench/td3 --force --episodes 0
	$(VENV)/bin/embedrl bench-target --export-dir $(OUT)/bench/td3 --emx $(EMX) --json $(OUT)/bench/target.json
	for q in int8 int8-weights q15; do \
	    $(VENV)/bin/embedrl export policies/static/td3.zip --out $(OUT)/bench/td3-target-$$q --force \
	        --episodes 0 --quantize $$q && $(VENV)/bin/embedrl bench-target \
	        --export-dir $(OUT)/bench/td3-target-$$q --json $(OUT)/bench/target-$$q.json || exit 1; \
	done

# A TD3 with the study's 6-100-100-2 actor trained in a minute by imitating the potential-field controller
# (independent of the shipped policies), exported with the full verification (10,000 samples, 200 episodes).
export-example: $(STAMP) ## an example TD3 trained by imitation in a minute, exported and verified
	$(PY) -m embedrl.export.example $(OUT)/example/td3.zip
	$(VENV)/bin/embedrl export $(OUT)/example/td3.zip --out $(OUT)/example/export --force \
	    --episodes $(EXAMPLE_EPISODES)

# The same policy on bare-metal Cortex-M4F and Cortex-M3 under QEMU: float32, int8 and q15.
targets-example: deps $(STAMP) ## the example on Cortex-M4F and Cortex-M3 under QEMU: float32, int8, q15
	test -f $(OUT)/example/td3.zip || $(PY) -m embedrl.export.example $(OUT)/example/td3.zip
	$(VENV)/bin/embedrl export $(OUT)/example/td3.zip --out $(OUT)/example/float32 --force \
	    --target cortex-m4 --target cortex-m3 --episodes $(EXAMPLE_EPISODES)
	$(VENV)/bin/embedrl export $(OUT)/example/td3.zip --out $(OUT)/example/int8 --force --quantize int8 \
	    --target cortex-m4 --target cortex-m3 --episodes $(EXAMPLE_EPISODES)
	$(VENV)/bin/embedrl export $(OUT)/example/td3.zip --out $(OUT)/example/q15 --force --quantize q15 \
	    --target cortex-m4 --target cortex-m3 --episodes $(EXAMPLE_EPISODES)

clean: ## remove $(OUT), build folders and caches
	rm -rf $(OUT) build *.egg-info .pytest_cache .mypy_cache .ruff_cache

help: ## this list: each target and what it does
	@sed -n 's/^\([a-z-]*\):.*## \(.*\)/\1|\2/p' $(MAKEFILE_LIST) | awk -F'|' '{printf "  %-16s %s\n", $$1, $$2}' | sed 's|$$(OUT)|$(OUT)|g'
