# The two commands a newcomer needs:  make demo  and  make test.
# make check is the everyday fast lane: lint, types and the unit tests (the full suite,
# closed-loop flights included, is make test, which CI runs).
# Each creates .venv if missing, installs the project with the extras it needs (only when
# pyproject.toml changed), installs the Debian packages it needs when run as root (otherwise
# says which), and then runs.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
DEB_PACKAGES := mosquitto libusb-1.0-0 libgomp1 systemd openssl libstdc++6 libgcc-s1
DEMO_OUT ?= out/demo

.PHONY: demo test check lint bench-quick deps-debian clean

demo: $(VENV)/.stamp-sim deps-debian
	$(PY) -m companion demo --out $(DEMO_OUT)

test: $(VENV)/.stamp-dev deps-debian
	$(PY) -m pytest

check: $(VENV)/.stamp-dev
	$(VENV)/bin/ruff check semmap planner companion tests bench
	$(VENV)/bin/mypy
	$(PY) -m pytest tests/unit -m "not slow" -q

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(VENV)/.stamp-sim: pyproject.toml | $(VENV)/bin/python
	$(PY) -m pip install --quiet -e '.[sim]'
	touch $@

$(VENV)/.stamp-dev: pyproject.toml | $(VENV)/bin/python
	$(PY) -m pip install --quiet -e '.[sim,dev]'
	touch $@ $(VENV)/.stamp-sim

deps-debian:
	@missing=""; for p in $(DEB_PACKAGES); do \
	  dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else \
	    echo "please install these Debian packages (as root):  apt-get install -y$$missing"; \
	  fi; \
	fi

clean:
	rm -rf $(VENV) out .pytest_cache
