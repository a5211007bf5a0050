# pyrtu: the two set-up commands of the README.
#   make demo   set up (venv, packages, C core) and run the main job
#   make test   set up and run the whole test suite (C core and pure-Python twin)
# Also: make test-asan (the suite against a C core built with ASan/UBSan), make bench.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
APT_PACKAGES := libmodbus-dev pkg-config socat

.PHONY: demo test test-asan bench lint setup system-packages

# Developer targets compile the C core with -Werror (PYRTU_STRICT_BUILD=1, read by
# pyrtu/_build_core.py), so that it stays -Wall -Wextra clean; `make demo` builds
# it as a user's `pip install .` does, where a new compiler's warning is no error.
setup test test-asan bench lint: export PYRTU_STRICT_BUILD := 1

demo: $(STAMP)
	$(PY) -m pyrtu demo

test: setup
	$(PY) -m pytest -q tests

setup: $(STAMP)

# Debian packages the interop tests need (libmodbus peers, socat pty pairs).
system-packages:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else echo "pyrtu: please install:$$missing (sudo apt-get install$$missing)"; exit 1; fi; \
	fi

$(STAMP): pyproject.toml setup.py pyrtu/_build_core.py pyrtu/_cdef.h $(wildcard csrc/*.c csrc/*.h) | system-packages
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	$(PY) -c "import pyrtu; print('pyrtu backend:', pyrtu.BACKEND)"
	@$(PY) -c "import pyrtu, sys; sys.exit(pyrtu.BACKEND != 'c')" || echo "*** pyrtu: the C" \
	  "core did not build; the pure-Python twin runs. Why: $(PY) -m pip install -v -e ." >&2
	touch $(STAMP)

# The whole suite against a C core built with -fsanitize=address,undefined
# (but the wall_clock tests: the sanitizer's allocator slows every thread).
ASAN_DIR := build/asan
test-asan: setup
	rm -rf $(ASAN_DIR) && mkdir -p $(ASAN_DIR)
	cp -r pyrtu tests csrc setup.py pyproject.toml README.md $(ASAN_DIR)/ && rm -f $(ASAN_DIR)/pyrtu/*.so
	PYRTU_SANITIZE=1 PYRTU_REQUIRE_C=1 $(PY) setup.py -q build_ext --build-lib $(ASAN_DIR) --build-temp build/asan-tmp --force
	cd $(ASAN_DIR) && \
	  LD_PRELOAD="$$(gcc -print-file-name=libasan.so) $$(gcc -print-file-name=libubsan.so)" \
	  ASAN_OPTIONS=detect_leaks=0:abort_on_error=1 UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 \
	  PYRTU_REQUIRE_C=1 ../../$(PY) -c "import pyrtu, sys; assert pyrtu.BACKEND == 'c' and '$(ASAN_DIR)' in pyrtu.__file__, pyrtu.__file__; print('sanitized core:', pyrtu.__file__)" && \
	  LD_PRELOAD="$$(gcc -print-file-name=libasan.so) $$(gcc -print-file-name=libubsan.so)" \
	  ASAN_OPTIONS=detect_leaks=0:abort_on_error=1 UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 \
	  PYRTU_REQUIRE_C=1 ../../$(PY) -m pytest -q -p no:cacheprovider -m 'not wall_clock' tests

bench: setup
	$(PY) bench/report.py

lint: setup
	$(PY) -m ruff check pyrtu tests bench
	$(PY) -m ruff format --check pyrtu tests bench
	$(PY) -m mypy
