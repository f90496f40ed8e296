# Two commands do all the set-up on a fresh Debian machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
LLVM19 := /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1

.PHONY: demo test lint llvm bench clean

# Debian's default libLLVM 15 crashes Dr.Jit on AVX-512 CPUs; install libllvm19 when missing.
llvm:
	@if [ "$$(uname -s)" = Linux ] && [ -f /etc/debian_version ] && ! ls /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1 \
	    && ! ls /usr/lib/*/libLLVM-1[6-9]*.so* /usr/lib/*/libLLVM.so.2* >/dev/null 2>&1; then \
	  echo "Installing Debian's libllvm19 (Dr.Jit needs libLLVM >= 16)"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq libllvm19; \
	fi

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

# path and segment_bdf for 20 s each on the caustic scene at 256x256: out/demo.png, out/demo_<method>.exr
demo: llvm $(STAMP)
	$(PY) -m segmitsuba.demo --out out

# one pytest worker per core, at most four: on a fresh clone LLVM compiles ~3000 kernels, one at a time per process
# (470 s of a single process's 1330 s of CPU), while the others wait
test: llvm $(STAMP)
	$(VENV)/bin/ruff check segmitsuba tests
	$(PY) -m pytest -q -n auto --maxprocesses 4

bench: llvm $(STAMP)
	$(VENV)/bin/segmitsuba bench

clean:
	rm -rf $(VENV) out build *.egg-info
