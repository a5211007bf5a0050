# pyrtu: the two set-up commands of the README.
#   make demo   set up (venv, packages, C core) and run the main job
#   make test   set up and run the whole test suite (C core and pure-Python twin); with
#               CI=true a test that skips fails (tests/conftest.py ALLOWED_SKIPS excepted)
# Also: make test-asan (the suite against a C core built with ASan/UBSan), make bench,
# make fuzz (the libFuzzer harnesses of fuzz/, FUZZ_SECONDS each), make fuzz-ci,
# make compat-matrix (the pymodbus drop-in's tests against every tested pymodbus).

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
APT_PACKAGES := libmodbus-dev pkg-config socat mosquitto mosquitto-clients strace prometheus clang-format
# the Windows cross compiler of `make cross-windows`
APT_PACKAGES += mingw-w64
# GNU time: bench/bench_capture.py's peak RSS of a child (its own, not its forking parent's)
APT_PACKAGES += time
# OpenSSL's headers: the C core's TLS of mbaps:// (csrc/rtu_tls_io.c; without them
# the core builds without it and mbaps:// runs over Python's ssl module)
APT_PACKAGES += libssl-dev
# The C sources make format-c formats and make lint checks (.clang-format).
C_SOURCES := $(wildcard csrc/*.c csrc/*.h csrc/python/*.c fuzz/*.c fuzz/*.h tests/core/csrc/*.c)
CLANG_FORMAT ?= $(shell command -v clang-format || command -v clang-format-14 || echo clang-format)

.PHONY: demo test test-asan compat-matrix bench bench-report docs lint format-c mutate mutate-faults setup system-packages fuzz fuzz-ci fuzz-build fuzz-packages \
	fuzz-python fuzz-outbox cross-windows wheel

# Developer targets compile the C core with -Werror (PYRTU_STRICT_BUILD=1, read by
# pyrtu/core/_build_core.py), so that it stays -Wall -Wextra clean; `make demo` builds
# it as a user's `pip install .` does, where a new compiler's warning is no error.
setup test test-asan bench bench-report lint mutate mutate-faults: export PYRTU_STRICT_BUILD := 1

demo: $(STAMP)
	$(PY) -m pyrtu demo

# -rs: every skip is listed with its reason.  With CI=true (CI, .ci/run) a skip fails
# the run unless tests/conftest.py's ALLOWED_SKIPS lists it.
test: setup
	$(PY) -m pytest -q -rs tests

setup: $(STAMP)

# Debian packages the tests need (libmodbus peers, socat pty pairs, the MQTT broker,
# strace for the outbox's durability tests: tests/outbox/test_durability.py,
# prometheus scraping --metrics: tests/metrics/; clang-format for make lint's check of
# the C sources).
system-packages:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get -o DPkg::Lock::Timeout=600 update -qq && DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq $$missing; \
	  else echo "pyrtu: please install:$$missing (sudo apt-get install$$missing)"; exit 1; fi; \
	fi

$(STAMP): pyproject.toml setup.py pyrtu/core/_build_core.py pyrtu/core/_cdef.h $(wildcard csrc/*.c csrc/*.h csrc/python/*.c) | system-packages
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	$(PY) -c "import pyrtu; print('pyrtu backend:', pyrtu.BACKEND)"
	@$(PY) -c "import pyrtu, sys; sys.exit(pyrtu.BACKEND != 'c')" || echo "*** pyrtu: the C" \
	  "core did not build; the pure-Python twin runs. Why: $(PY) -m pip install -v -e ." >&2
	touch $(STAMP)

# The whole suite against a C core built with -fsanitize=address,undefined
# (but the wall_clock and rss tests: the sanitizer's allocator slows every thread and
# keeps freed memory in quarantine).
ASAN_DIR := build/asan
test-asan: setup
	rm -rf $(ASAN_DIR) && mkdir -p $(ASAN_DIR)
	cp -r pyrtu tests csrc bench docs fuzz mutate .ci setup.py pyproject.toml MANIFEST.in README.md LICENSE CHANGELOG.md mkdocs.yml Makefile .clang-format $(ASAN_DIR)/ && rm -f $(ASAN_DIR)/pyrtu/*.so
	PYRTU_SANITIZE=1 PYRTU_REQUIRE_C=1 $(PY) setup.py -q build_ext --build-lib $(ASAN_DIR) --build-temp build/asan-tmp --force
	cd $(ASAN_DIR) && \
	  LD_PRELOAD="$$(gcc -print-file-name=libasan.so) $$(gcc -print-file-name=libubsan.so)" \
	  ASAN_OPTIONS=detect_leaks=0:abort_on_error=1 UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 \
	  PYRTU_REQUIRE_C=1 ../../$(PY) -c "import pyrtu, sys; assert pyrtu.BACKEND == 'c' and '$(ASAN_DIR)' in pyrtu.__file__ and '$(ASAN_DIR)' in pyrtu.core._cext.CRCFAST.__file__, pyrtu.__file__; print('sanitized core:', pyrtu.__file__)" && \
	  LD_PRELOAD="$$(gcc -print-file-name=libasan.so) $$(gcc -print-file-name=libubsan.so)" \
	  ASAN_OPTIONS=detect_leaks=0:abort_on_error=1 UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 \
	  PYRTU_REQUIRE_C=1 ../../$(PY) -m pytest -q -rs -p no:cacheprovider -m 'not wall_clock and not rss' tests

# Every benchmark of bench/README.md once, then bench/RESULTS.md written from that run
# (BENCH_ARGS=--quick: fewer rounds; BENCH_ARGS="--only crc,core": some of them);
# make bench-report writes RESULTS.md again from bench/results/ without measuring.
BENCH_ARGS ?=

# The pymodbus compat tests against each release of pyrtu.compat.PYMODBUS_RELEASES
# (3.9 .. 3.16), one virtual environment each under build/compat-matrix/ (kept between
# runs), pyrtu and its C core from this tree: tests/compat/matrix.py, docs/COMPAT.md.
COMPAT_JOBS ?= 2
compat-matrix: setup
	$(PY) tests/compat/matrix.py --jobs $(COMPAT_JOBS)

bench: setup
	$(PY) bench/report.py $(BENCH_ARGS)

bench-report: setup
	$(PY) bench/report.py --render

# The C core's portable sources (all of csrc/ but the POSIX I/O files csrc/rtu_*_io.c,
# which pyrtu/core/_build_core.py leaves out on Windows) compiled by a Windows
# toolchain, Debian's mingw-w64, -Werror, then linked into a DLL (every symbol they
# use must resolve without the POSIX files).  CI runs it (.ci/run).
MINGW_CC ?= x86_64-w64-mingw32-gcc
CROSS_DIR := build/cross-windows
CROSS_SOURCES := $(filter-out %_io.c,$(wildcard csrc/*.c))
cross-windows: | system-packages
	rm -rf $(CROSS_DIR) && mkdir -p $(CROSS_DIR)
	for f in $(CROSS_SOURCES); do \
	  $(MINGW_CC) -std=c99 -O2 -Wall -Wextra -Werror -Icsrc -c $$f -o $(CROSS_DIR)/$$(basename $$f .c).o || exit 1; \
	done
	$(MINGW_CC) -shared -o $(CROSS_DIR)/rtu_core.dll $(CROSS_DIR)/*.o -Wl,--no-undefined
	@echo "cross-windows: $(words $(CROSS_SOURCES)) files compiled and linked: $(CROSS_DIR)/rtu_core.dll"

# An sdist and a wheel (python -m build), the wheel repaired by auditwheel to the
# manylinux tag its symbols allow, into dist/ (docs/INSTALL.md).
wheel: setup
	rm -rf dist build/wheel && mkdir -p build/wheel
	PYRTU_REQUIRE_C=1 $(PY) -m build --outdir build/wheel .
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(PY) -m auditwheel repair --strip --wheel-dir dist build/wheel/*.whl
	cp build/wheel/*.tar.gz dist/
	$(PY) -m abi3audit --strict --report dist/*.whl
	ls -l dist

# Mutation testing (mutate/run.py; docs/MUTATION.md): `make mutate` runs cosmic-ray over
# the modules of mutate/targets.toml and writes docs/MUTATION.md (hours on 2 cores;
# MUTATE_TARGETS="plan schedule" for some, MUTATE_JOBS=2 for targets in parallel);
# `make mutate-faults` applies the hand-written faults of mutate/faults.toml (Python
# and C) one at a time and fails if any survives (CI runs it).
MUTATE_TARGETS ?=
MUTATE_JOBS ?= 1
mutate: setup
	@$(PY) -c "import cosmic_ray" 2>/dev/null || $(PY) -m pip install -q 'cosmic-ray>=8.4,<9'
	$(PY) mutate/run.py generated --jobs $(MUTATE_JOBS) $(MUTATE_TARGETS)

mutate-faults: setup
	$(PY) mutate/run.py faults

# The documentation site (mkdocs.yml) into build/site; --strict: a warning fails it.
docs: setup
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict

lint: setup
	$(PY) -m ruff check pyrtu tests bench mutate docs/hooks.py
	$(PY) -m ruff format --check pyrtu tests bench mutate docs/hooks.py
	$(PY) -m mypy
	$(CLANG_FORMAT) --dry-run --Werror $(C_SOURCES)

format-c:
	$(CLANG_FORMAT) -i $(C_SOURCES)

# libFuzzer harnesses (fuzz/*.c) built with clang and ASan/UBSan.  The seeds in
# fuzz/corpus/<name>/ (fuzz/make_corpus.py) are read first; new inputs go to
# build/fuzz/corpus/<name>/, crashes to build/fuzz/crash-<name>-*.
#   make fuzz                  each harness for FUZZ_SECONDS (default 300)
#   make fuzz FUZZ_SECONDS=3600 FUZZ_ARGS=-max_len=300
#   make fuzz-python           the atheris harness of the Python layer, FUZZ_SECONDS
#   make fuzz-ci               each briefly (about a minute in all); fails on any crash
FUZZ_APT_PACKAGES := clang-14 libfuzzer-14-dev libclang-rt-14-dev
CLANG ?= clang-14
FUZZ_SECONDS ?= 300
FUZZ_CI_SECONDS ?= 10
FUZZ_ARGS ?=
FUZZ_HARNESSES := stream framer predict crc mbap vbus tcp mux image serve
FUZZ_DIR := build/fuzz
FUZZ_CFLAGS := -std=c99 -g -O2 -Wall -Wextra -Werror -Icsrc \
  -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=undefined
# the CRC harness runs the folding code at every length (see csrc/rtu_crc.c)
FUZZ_CRC_DEFS := -DRTU_CLMUL_MIN=16 -DRTU_VCLMUL_MIN=2 -DRTU_DISPATCH_CLMUL=1 -DRTU_DISPATCH_VCLMUL=2

fuzz-packages:
	@missing=""; for p in $(FUZZ_APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get -o DPkg::Lock::Timeout=600 update -qq && DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq $$missing; \
	  else echo "pyrtu: please install:$$missing (sudo apt-get install$$missing)"; exit 1; fi; \
	fi

# the core without its TLS (csrc/rtu_tls_io.c needs OpenSSL; no harness reaches it)
FUZZ_CORE := $(filter-out csrc/rtu_tls_io.c,$(wildcard csrc/*.c))

$(FUZZ_DIR)/fuzz_%: fuzz/fuzz_%.c fuzz/fuzz_common.h $(wildcard csrc/*.c csrc/*.h) | fuzz-packages
	mkdir -p $(FUZZ_DIR)
	$(CLANG) $(FUZZ_CFLAGS) $(if $(filter crc,$*),$(FUZZ_CRC_DEFS)) $< $(FUZZ_CORE) -o $@

fuzz-build: $(addprefix $(FUZZ_DIR)/fuzz_,$(FUZZ_HARNESSES))

fuzz: fuzz-build
	@for h in $(FUZZ_HARNESSES); do \
	  mkdir -p $(FUZZ_DIR)/corpus/$$h; echo "== fuzz_$$h: $(FUZZ_SECONDS) s"; \
	  $(FUZZ_DIR)/fuzz_$$h -max_total_time=$(FUZZ_SECONDS) -print_final_stats=1 $(FUZZ_ARGS) \
	    -artifact_prefix=$(FUZZ_DIR)/crash-$$h- $(FUZZ_DIR)/corpus/$$h fuzz/corpus/$$h \
	    2>$(FUZZ_DIR)/fuzz_$$h.log || { tail -40 $(FUZZ_DIR)/fuzz_$$h.log; exit 1; }; \
	  grep -E '^stat::(number_of_executed_units|average_exec_per_sec)' $(FUZZ_DIR)/fuzz_$$h.log; \
	done

# The Python layer (fuzz/fuzz_python.py): atheris from PyPI, into the venv.
fuzz-python: setup
	@$(PY) -c "import atheris" 2>/dev/null || $(PY) -m pip install -q atheris
	mkdir -p $(FUZZ_DIR)/corpus/python
	$(PY) fuzz/fuzz_python.py -max_total_time=$(FUZZ_SECONDS) -print_final_stats=1 $(FUZZ_ARGS) \
	  -artifact_prefix=$(FUZZ_DIR)/crash-python- $(FUZZ_DIR)/corpus/python \
	  2>$(FUZZ_DIR)/fuzz_python.log || { tail -40 $(FUZZ_DIR)/fuzz_python.log; exit 1; }
	@grep -E '^stat::(number_of_executed_units|average_exec_per_sec)' $(FUZZ_DIR)/fuzz_python.log

# The bridge outbox's file format (fuzz/fuzz_outbox.py), atheris like fuzz-python.
fuzz-outbox: setup
	@$(PY) -c "import atheris" 2>/dev/null || $(PY) -m pip install -q atheris
	mkdir -p $(FUZZ_DIR)/corpus/outbox
	$(PY) fuzz/fuzz_outbox.py -max_total_time=$(FUZZ_SECONDS) -print_final_stats=1 $(FUZZ_ARGS) \
	  -artifact_prefix=$(FUZZ_DIR)/crash-outbox- $(FUZZ_DIR)/corpus/outbox \
	  2>$(FUZZ_DIR)/fuzz_outbox.log || { tail -40 $(FUZZ_DIR)/fuzz_outbox.log; exit 1; }
	@grep -E '^stat::(number_of_executed_units|average_exec_per_sec)' $(FUZZ_DIR)/fuzz_outbox.log

fuzz-ci:
	$(MAKE) fuzz FUZZ_SECONDS=$(FUZZ_CI_SECONDS)
	$(MAKE) fuzz-python FUZZ_SECONDS=$(FUZZ_CI_SECONDS)
	$(MAKE) fuzz-outbox FUZZ_SECONDS=$(FUZZ_CI_SECONDS)
