# cellbench — the two commands a fresh Debian machine needs: `make run` and `make test`.
BUILD   ?= build
JOBS    ?= $(shell nproc)
SHARED  ?= $(abspath ../shared)
DATA    := $(SHARED)/data/p45b
BIN     := $(BUILD)/bin
# Every `make run` writes into its own folder (two at once never share a file, a database or a port).
OUT     := $(BUILD)/run/$(shell date -u +%Y%m%d-%H%M%S)-$(shell echo $$PPID)

# Debian packages the build and the tests need (installed by `make deps` when missing). nodejs and npm build the
# dashboard (web/), chromium and chromium-driver run its browser tests (poppler-utils renders the report's PDF); an npm that came with another nodejs
# package (NodeSource's provides it and conflicts with Debian's) counts as installed.
DEBS := cmake g++ make pkg-config ccache \
        libceres-dev libeigen3-dev libboost-dev libboost-system-dev libspdlog-dev nlohmann-json3-dev \
        libsqlite3-dev libmodbus-dev libcli11-dev libgtest-dev libgmock-dev libbenchmark-dev \
        python3 python3-numpy python3-scipy nodejs npm chromium chromium-driver poppler-utils clang libclang-rt-dev

.PHONY: all deps configure build run test test-loaded test-unit test-data bench prove clean install fuzz fuzz-long fuzz-configure soak mutate sanitize

all: build

deps:
	@missing=""; for p in $(DEBS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || \
	  { [ $$p = npm ] && command -v npm > /dev/null; } || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  if [ "$$(id -u)" -eq 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

configure: deps
	@cmake -S . -B $(BUILD) -DCMAKE_BUILD_TYPE=Release -DCELLBENCH_SHARED_DIR=$(SHARED) > $(BUILD).configure.log 2>&1 \
	  || (cat $(BUILD).configure.log; exit 1)

build: configure
	cmake --build $(BUILD) -j$(JOBS)

# The main job. For now (before the daemon lands): fit the real P45B HPPC + 4C discharge, then simulate the
# Random Walk — a profile the fit never saw — with the fitted parameters and with the thesis' own.
run: build
	@mkdir -p $(OUT)
	$(BIN)/cellbench import --neware $(DATA)/hppc_1c_30degC_neware.csv --bdf $(DATA)/hppc_1c_30degC.bdf.csv -o $(OUT)/hppc.bdf.csv
	$(BIN)/cellbench import --neware $(DATA)/rw_30degC_neware.csv --dewesoft $(DATA)/rw_30degC_dewesoft.csv -o $(OUT)/rw.bdf.csv
	$(BIN)/cellbench fit $(OUT)/hppc.bdf.csv $(DATA)/cc_4c_30degC.bdf.csv --cell "Molicel INR-21700-P45B" -o $(OUT)/p45b.params.json --json $(OUT)/fit-summary.json
	@echo "== Random Walk, thesis parameters (config/cells/p45b-thesis.json)"
	$(BIN)/cellbench simulate --params config/cells/p45b-thesis.json $(OUT)/rw.bdf.csv --json $(OUT)/rw-thesis.metrics.json
	@echo "== Random Walk, parameters fitted by cellbench"
	$(BIN)/cellbench simulate --params $(OUT)/p45b.params.json $(OUT)/rw.bdf.csv --json $(OUT)/rw-fitted.metrics.json --out $(OUT)/rw-fitted.sim.bdf.csv
	@echo "outputs in $(OUT)/"
	@# The daemon on the simulated bench (every instrument hosted by cellbenchd on loopback, 100x bench time):
	@# a short HPPC through the client, then the fitted table from GET /runs/{id}/fits, then SIGTERM.
	@echo "== cellbenchd on the simulated bench: short HPPC (config/programs/hppc_short.json) at 100x"
	@# The daemon listens on a free port (--listen 127.0.0.1:0) and prints the address it bound; its simulated
	@# instruments take free ports and a socket path of their own (in the log), the database is this run's.
	@set -e; out=$(abspath $(OUT)); db=$$out/bench.sqlite; tok=run-$$$$; url=""; \
	rm -f $$db $$db-wal $$db-shm; \
	$(BIN)/cellbenchd --config config/bench.sim.json --listen 127.0.0.1:0 --db $$db --token $$tok \
	  --time-scale 100 > $$out/cellbenchd.out 2> $$out/cellbenchd.log & pid=$$!; \
	trap 'kill -TERM $$pid 2>/dev/null || true; wait $$pid 2>/dev/null || true' EXIT; \
	for i in $$(seq 300); do url=$$(sed -n 's|^cellbenchd: API \(http://[^ ]*\)/api/v1$$|\1|p' $$out/cellbenchd.out); \
	  [ -n "$$url" ] && $(BIN)/cellbench status --server $$url > /dev/null 2>&1 && break; \
	  kill -0 $$pid 2>/dev/null || { cat $$out/cellbenchd.log; exit 1; }; sleep 0.1; done; \
	[ -n "$$url" ] || { echo "cellbenchd printed no API address"; cat $$out/cellbenchd.log; exit 1; }; \
	echo "cellbenchd at $$url/api/v1, database $$db"; \
	sed -n 's/.*\(simulated [a-z]* (hosted) .*\)/  \1/p' $$out/cellbenchd.log; \
	$(BIN)/cellbench start --program hppc_short --cell p45b --server $$url --token $$tok --follow; \
	/usr/bin/python3 -c 'import json, sys, urllib.request as u; api = sys.argv[1] + "/api/v1"; \
	get = lambda p: json.load(u.urlopen(api + p)); run = get("/runs")["runs"][0]; \
	print("== run %s (%s): fitted pulse sets, GET /api/v1/runs/%s/fits" % (run["id"], run["state"], run["id"])); \
	print("%3s %6s %8s %9s %9s %9s %9s %9s %9s" % ("set", "SOC", "OCV V", "R0d mOhm", "R1d mOhm", "C1d F", "R2d mOhm", "C2d F", "R0c mOhm")); \
	f = lambda d, k, s=1.0: ("%9.3f" % (d[k] * s)) if d and d.get(k) is not None else "%9s" % "-"; \
	[print("%3d %6.3f %8.4f %s %s %s %s %s %s" % (x["pulse_set"], x["soc"], x["ocv_v"], f(x["discharge"], "r0_ohm", 1e3), \
	  f(x["discharge"], "r1_ohm", 1e3), f(x["discharge"], "c1_f"), f(x["discharge"], "r2_ohm", 1e3), f(x["discharge"], "c2_f"), \
	  f(x["charge"], "r0_ohm", 1e3))) for x in get("/runs/%s/fits" % run["id"])["fits"]]' $$url; \
	echo "API $$url/api/v1 (token $$tok), database $$db, daemon log $$out/cellbenchd.log"; \
	kill -TERM $$pid; wait $$pid; trap - EXIT; echo "cellbenchd stopped (SIGTERM)"

# The fuzz targets compile (one job, clang, $(FUZZ_BUILD).build.log) while the tests run: the HIL tests leave
# CPU idle waiting on the simulated bench, and the fuzz build no longer adds its two minutes at the end.
test: build fuzz-configure
	@( cmake --build $(FUZZ_BUILD) -j1 > $(FUZZ_BUILD).build.log 2>&1 ) & fuzz_build=$$!; \
	  ( cd $(BUILD) && ctest --output-on-failure -j$(JOBS) --timeout 600 ); tests=$$?; \
	  wait $$fuzz_build || { tail -40 $(FUZZ_BUILD).build.log; echo "fuzz build failed: $(FUZZ_BUILD).build.log"; exit 1; }; \
	  exit $$tests
	cd $(FUZZ_BUILD) && ctest --output-on-failure -j$(JOBS) -L fuzz

# libFuzzer targets (tests/fuzz/: instrument frames, recordings, configs, HTTP requests) under ASan + UBSan, in
# a clang build of just the code they test; each runs FUZZ_SECONDS from its seed corpus, a crash fails.
# `make test` runs them briefly; a longer run: `make fuzz FUZZ_SECONDS=1800 FUZZ_OPT=-O1` (README, "Fuzzing").
FUZZ_BUILD   ?= $(BUILD)-fuzz
FUZZ_SECONDS ?= 5
FUZZ_OPT     ?= -O0
fuzz-configure: deps
	@cmake -S . -B $(FUZZ_BUILD) -DCELLBENCH_FUZZ_ONLY=ON -DCMAKE_CXX_COMPILER=clang++ -DCMAKE_BUILD_TYPE=Debug \
	  -DCELLBENCH_FUZZ_SECONDS=$(FUZZ_SECONDS) -DCELLBENCH_FUZZ_OPT=$(FUZZ_OPT) > $(FUZZ_BUILD).configure.log 2>&1 || (cat $(FUZZ_BUILD).configure.log; exit 1)

fuzz: fuzz-configure
	cmake --build $(FUZZ_BUILD) -j$(JOBS)
	cd $(FUZZ_BUILD) && ctest --output-on-failure -j$(JOBS) -L fuzz

# Issue 14's acceptance: the `hil` label LOADED_RUNS times in a row while a load generator keeps every core busy
# (one shell busy-loop per core at nice LOAD_NICE; LOAD_NICE=0 competes with the tests as an equal). A healthy
# simulated run must never abort because of load: the simulated bench slows down with the daemon instead.
LOAD_NICE   ?= 10
LOAD_JOBS   ?= $(shell nproc)
LOADED_RUNS ?= 3
test-loaded: build
	@set -e; pids=""; \
	for k in $$(seq $(LOAD_JOBS)); do nice -n $(LOAD_NICE) sh -c 'while :; do :; done' & pids="$$pids $$!"; done; \
	trap 'kill $$pids 2>/dev/null || true' EXIT INT TERM; \
	echo "load: $(LOAD_JOBS) busy loops at nice $(LOAD_NICE) (pids$$pids)"; \
	for run in $$(seq $(LOADED_RUNS)); do \
	  echo "== hil under load, run $$run of $(LOADED_RUNS)"; \
	  ( cd $(BUILD) && ctest --output-on-failure -j$(JOBS) --timeout 600 -L hil ) || { echo "hil failed under load in run $$run"; exit 1; }; \
	done; \
	echo "hil passed $(LOADED_RUNS) times in a row under load"

# Issue 16's acceptance run: every target 10 minutes from its corpus, optimised for speed (-O1; a full rebuild of
# $(FUZZ_BUILD) the first time). About 7 targets x 10 min / $(JOBS) jobs of wall time. `make fuzz` stays short.
FUZZ_LONG_SECONDS ?= 600
fuzz-long:
	$(MAKE) fuzz FUZZ_SECONDS=$(FUZZ_LONG_SECONDS) FUZZ_OPT=-O1

# The unit and HIL tests built with AddressSanitizer and UndefinedBehaviorSanitizer (gcc -O1, $(SAN_BUILD): a full
# build of its own, about an hour on 2 cores the first time with other work beside it). A leak, an out-of-bounds
# access, a use after free or undefined behaviour (signed overflow, a misaligned or null access, a bad enum or
# bool) fails its test.
# Not part of `make test`; docs/testing.md, "Sanitizers". Eigen switches to its own aligned allocator when it sees
# ASan, and Debian's libceres (built without) frees such a block with free(): a bad-free in every covariance.
# EIGEN_MALLOC_ALREADY_ALIGNED=1 keeps the allocator libceres was built with (glibc's and ASan's malloc align to 16).
SAN_BUILD  ?= $(BUILD)-asan
SAN_LABELS ?= unit|hil
# The full HPPC at x800 outruns the pacing under ASan: the slower daemon's tester readings lag for a whole grace
# of wall time (10 s), which the pacing takes as a real silence, and the run aborts as designed. No sanitizer report.
SAN_EXCLUDE ?= DaemonHil.FullHppcStoresEveryStep
SAN_FLAGS  := -O1 -g -fsanitize=address,undefined -fno-omit-frame-pointer -fno-sanitize-recover=undefined \
              -DEIGEN_MALLOC_ALREADY_ALIGNED=1
sanitize: deps
	@cmake -S . -B $(SAN_BUILD) -DCMAKE_BUILD_TYPE=Debug -DCMAKE_CXX_FLAGS="$(SAN_FLAGS)" \
	  -DCMAKE_EXE_LINKER_FLAGS="-fsanitize=address,undefined" > $(SAN_BUILD).configure.log 2>&1 \
	  || (cat $(SAN_BUILD).configure.log; exit 1)
	cmake --build $(SAN_BUILD) -j$(JOBS)
	cd $(SAN_BUILD) && ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1 \
	  ctest --output-on-failure -j$(JOBS) --timeout 1800 -L '$(SAN_LABELS)' -E '$(SAN_EXCLUDE)'

test-unit: build
	cd $(BUILD) && ctest --output-on-failure -j$(JOBS) -L unit

test-data: build
	cd $(BUILD) && ctest --output-on-failure -j$(JOBS) -L data

# Every Google Benchmark program (the default build compiles them; BENCH_MIN_TIME seconds per benchmark unless
# it sets its own), then the scipy baseline of the thesis' method on the same HPPC file when python3-scipy is
# installed. BENCH_FILTER narrows the run (a --benchmark_filter regex).
BENCH_MIN_TIME ?= 0.2
BENCH_FILTER   ?= .
bench: build
	@for b in $(BIN)/*_bench; do echo "== $$b"; \
	  $$b --benchmark_counters_tabular=true --benchmark_min_time=$(BENCH_MIN_TIME) --benchmark_filter='$(BENCH_FILTER)' || exit 1; done
	@if /usr/bin/python3 -c 'import numpy, scipy' 2> /dev/null; then \
	  echo "== bench/scipy_baseline.py (the thesis' per-segment fits, scipy curve_fit)"; \
	  /usr/bin/python3 bench/scipy_baseline.py $(DATA)/hppc_1c_30degC.bdf.csv; \
	else echo "== bench/scipy_baseline.py skipped: python3-scipy is not installed"; fi

# The soak campaign (issue 6; not part of `make test`): SOAK_HOURS of bench time (CC, short HPPC, Random Walk at
# 25 and 40 degC) at SOAK_SCALE x against a real cellbenchd, instrument faults injected at random; report in
# $(BUILD)/soak/report.md (README "Operations"). The defaults take about 8 minutes of wall time.
SOAK_HOURS ?= 12
SOAK_SCALE ?= 100
SOAK_SEED  ?= 6
soak: build
	cmake --build $(BUILD) -j$(JOBS) --target cellbench_soak
	$(BIN)/cellbench_soak --hours $(SOAK_HOURS) --time-scale $(SOAK_SCALE) --seed $(SOAK_SEED) --report $(BUILD)/soak/report.md

# The mutation campaign of the recording readers (issue 16): MUTATE_COUNT mutated files of each kind (BDF CSV,
# Neware export, DewesoftX export) made from the real recordings, the CLI run on each with a 10 s timeout;
# prints the table of crashes, hangs, clear errors, right successes and silently wrong successes.
MUTATE_COUNT ?= 300
MUTATE_JOBS ?= 1
mutate: build
	/usr/bin/python3 scripts/mutate_inputs.py --bin $(BIN) --data $(DATA) --count $(MUTATE_COUNT) --jobs $(MUTATE_JOBS)

# The proof of `cellbench diagnose` on the independent plant (SEEDS=N: seeds 1..N, or a list "1 4 7"); CATALOGUE=1
# adds the cheaper table of the catalogue against itself.
SEEDS ?= 5
prove: build
	scripts/prove.sh $(BIN) "$(SEEDS)" $(BUILD)/prove

# Installs what `make` built (bin/, share/cellbench/config, lib/systemd/system/cellbenchd.service) under PREFIX:
# `make && sudo make install` (README "Running as a service"). Does not build, so root never writes to $(BUILD).
PREFIX ?= /usr/local
install:
	@test -x $(BIN)/cellbenchd || { echo "nothing built in $(BUILD)/: run make first (as yourself), then sudo make install"; exit 1; }
	cmake --install $(BUILD) --prefix $(PREFIX)

clean:
	rm -rf $(BUILD) $(BUILD).configure.log
