# `make demo` and `make test` install everything on a fresh Debian machine (as root), then run.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
APT_PACKAGES := python3 python3-venv python3-dev gcc g++ libc6-dev make pkg-config iproute2 \
	aravis-tools aravis-tools-cli gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev \
	chromium chromium-driver systemd

.PHONY: demo test install system-deps bench clean

demo: install
	$(VENV)/bin/rig demo

# Three test processes on two cores, one thread each for torch, OpenCV and ONNX Runtime
# (tests/conftest.py): a quarter of the suite's time is tests waiting on real time (daemons,
# namespaced hosts, streams), which the third fills (747 s against 1035 s with two, here). The
# files in our order, the long ones first (pytest-xdist would put the files of most tests first,
# and the soak and the two-host tests, one test each, ran last, alone).
test: install
	$(PY) -m pytest -q -p no:cacheprovider -n 3 --dist loadfile --no-loadscope-reorder

install: $(STAMP)

# apt only when something is missing: re-running make stays fast and needs no network.
system-deps:
	@missing=$$(for p in $(APT_PACKAGES); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q 'install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then \
		echo "installing Debian packages:" $$missing; \
		apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $$missing; \
	fi

$(STAMP): pyproject.toml Makefile | system-deps
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[aravis,train,test]'
	touch $(STAMP)

bench: install
	for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache out
