# `make demo` and `make test` work on a fresh machine: each creates .venv on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup browser stream-tools demo test test-unit test-compose docker-engine locate-example clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet -e '.[test]'
	$(BIN)/python -m toptag.solvers.warmup  # the solvers' numba kernels into their on-disk cache
	$(BIN)/python -m sim.render_kernels  # and the renderer's
	touch $@

# The live view's browser test drives Debian's chromium headless (Playwright's own browser download
# does not work offline): installed here when missing, as root.
browser:
	@command -v chromium >/dev/null 2>&1 || (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null)

demo: setup
	$(BIN)/toptag demo --duration 60 --report demo-report.json

locate-example: setup
	$(BIN)/toptag locate --camera examples/rsu-sw-960x720.json --vehicle examples/bus-17.json examples/*.jpg

# Debian packages of the camera-stream tests: ffmpeg (H.264 encoding for `toptag sim record`) and
# gst-rtsp-server, run by the system python3 through python3-gi, serving the recorded video over RTSP.
# Installed when missing and root; otherwise those tests skip, naming what is missing.
STREAM_DEBS := ffmpeg python3-gi gir1.2-gst-rtsp-server-1.0 gstreamer1.0-plugins-good gstreamer1.0-plugins-bad

stream-tools:
	@if ! dpkg -s $(STREAM_DEBS) >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing $(STREAM_DEBS)"; \
	    export DEBIAN_FRONTEND=noninteractive; \
	    apt-get install -y -qq -o DPkg::Lock::Timeout=900 --no-install-recommends $(STREAM_DEBS) >/dev/null \
	      || { apt-get update -qq -o DPkg::Lock::Timeout=900 && apt-get install -y -qq -o DPkg::Lock::Timeout=900 --no-install-recommends $(STREAM_DEBS) >/dev/null; } \
	      || echo "could not install $(STREAM_DEBS): the stream tests will skip"; \
	  else echo "not root: $(STREAM_DEBS) not installed, the stream tests will skip"; fi; \
	fi

# Every test in one pytest run, spread over pytest-xdist workers (one per core and one more, see
# tests/conftest.py). The system tests (the demos, the deployment, the compose test: docker compose up for
# real, plain and secured, on a Docker engine that docker-engine installs where missing, skipped with the
# reason where Docker cannot run) are one xdist group: they run one after another on one worker, as each
# starts the whole system (tests/tiers.py). test-compose runs the compose test alone.
# The run lists its 15 slowest tests: what to look at when it nears its 10-minute budget.
test: setup docker-engine browser stream-tools
	$(BIN)/python -m pytest -q --durations=15 -n auto --dist loadgroup

test-compose: setup docker-engine
	$(BIN)/python -m pytest -q tests/test_compose.py

docker-engine:
	@sh tests/compose/install-docker.sh

test-unit: setup  # the fast tier: pure code, no network, no child process
	$(BIN)/python -m pytest -q -m unit

clean:
	rm -rf $(VENV) build *.egg-info
