# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: install demo test lint typecheck pytest system-deps bench clean compose-deps compose-test zenohd

$(STAMP): pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# System packages some tests need (a real browser for the console; nftables and iproute2
# for the NAT test). Installed with apt-get only when missing; tests skip with a reason
# where they cannot be had.
system-deps:
	@missing=""; \
	[ -x /usr/bin/chromium ] || missing="$$missing chromium"; \
	command -v nft >/dev/null 2>&1 || missing="$$missing nftables"; \
	command -v ip >/dev/null 2>&1 || missing="$$missing iproute2"; \
	if [ -n "$$missing" ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing:$$missing"; \
	  ($(SUDO) apt-get update -qq && $(SUDO) DEBIAN_FRONTEND=noninteractive \
	    apt-get install -y -qq --no-install-recommends $$missing >/dev/null) \
	  || echo "could not install$$missing; the tests that need them will be skipped"; \
	fi

demo: install
	$(BIN)/telerobot demo

# lint-imports checks the layered import contract in pyproject.toml (docs/architecture.md)
lint: install
	$(BIN)/ruff format --check .
	$(BIN)/ruff check .
	$(BIN)/lint-imports --no-cache

typecheck: install
	$(BIN)/mypy

# In three passes. Unit and property tests (most of the CPU) on three workers (pytest-xdist,
# `loadfile`: a module's shared fixtures start once); then the system, fault and browser
# tests on two workers (they wait more than they compute: one process used 0.9 of a
# core); then the `alone` ones, one at a time in one process: the decision's default
# 100 ms watchdogs, the 1 kHz force stream, processes stopped, killed and restarted. On two
# loaded cores a second worker beside these made a stream or a recovery miss its deadline
# (a SIGSTOPped force service not back within 20 s, 1 run in 3). PYTEST_WORKERS=0 runs the
# first two passes in one process too.
PYTEST_WORKERS ?= 2
# The unit pass waits more than it computes too (2 workers: 231 s at 120 % CPU on 2 cores;
# 3 workers: 183 s at 166 %; 4: 156 s at 176 %, and a router test then lost a sample).
UNIT_WORKERS   ?= $(if $(filter 0,$(PYTEST_WORKERS)),0,$(shell echo $$(( $(PYTEST_WORKERS) + 1 ))))
SERIAL_MARKS   := system or faults or browser
pytest: install system-deps
	$(BIN)/pytest -q -n $(UNIT_WORKERS) --dist loadfile -m "not ($(SERIAL_MARKS) or alone)"
	$(BIN)/pytest -q -n $(PYTEST_WORKERS) --dist loadfile -m "($(SERIAL_MARKS)) and not alone"
	$(BIN)/pytest -q -m "alone"

test: lint typecheck pytest

# The compose run (tests/deploy/test_compose.py, docs/deploy.md "Docker"): Docker's engine
# (Debian's docker.io), Compose v2 and debootstrap, for a base image made from Debian's
# packages where no image registry answers. Installed with apt-get only when missing, like
# system-deps; the test starts dockerd itself when it is not running. Where apt has only
# Compose v1 (bookworm's docker-compose 1.29, which refuses the files' top-level `name:`),
# Compose v2 is built from its Go module (go install) as Docker's CLI plugin.
COMPOSE_VERSION ?= v2.29.7
COMPOSE_PLUGIN  := /usr/local/lib/docker/cli-plugins/docker-compose
compose-deps:
	@missing=""; \
	command -v dockerd >/dev/null 2>&1 || missing="$$missing docker.io"; \
	command -v debootstrap >/dev/null 2>&1 || missing="$$missing debootstrap"; \
	docker compose version >/dev/null 2>&1 || command -v go >/dev/null 2>&1 \
	  || missing="$$missing golang-go"; \
	if [ -n "$$missing" ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing:$$missing"; \
	  ($(SUDO) apt-get update -qq && $(SUDO) DEBIAN_FRONTEND=noninteractive \
	    apt-get install -y -qq --no-install-recommends $$missing >/dev/null) \
	  || echo "could not install$$missing; the compose test will say what is missing"; \
	fi; \
	if ! docker compose version >/dev/null 2>&1 && command -v go >/dev/null 2>&1; then \
	  echo "building Compose $(COMPOSE_VERSION) (go install) into $(COMPOSE_PLUGIN)"; \
	  tmp=$$(mktemp -d); \
	  GOBIN=$$tmp go install -ldflags "-s -w -X github.com/docker/compose/v2/internal.Version=$(COMPOSE_VERSION)" \
	    github.com/docker/compose/v2/cmd@$(COMPOSE_VERSION) \
	  && $(SUDO) install -D -m 0755 $$tmp/cmd $(COMPOSE_PLUGIN) \
	  || echo "could not build Compose $(COMPOSE_VERSION); the compose test will say so"; \
	  rm -rf $$tmp; \
	fi

# Both compose stacks built and brought up on this host, checked from outside (minutes:
# the image build, then the stacks). Its own target, not part of `make test`.
compose-test: install compose-deps
	TELEROBOT_COMPOSE_TEST=1 $(BIN)/pytest -q -p no:xdist -s tests/deploy/test_compose.py

# zenohd, the Rust router (labs, rmw_zenoh, the eclipse/zenoh image), of the same release as
# the installed eclipse-zenoh, built once from the crate registry into ZENOHD_ROOT, where
# tests/deploy/test_zenohd.py and the compose test look for it. Needs cargo (rustup, or
# Debian's cargo if new enough); tens of minutes on two cores the first time.
ZENOHD_ROOT ?= $(HOME)/.cache/telerobot/zenohd-$$v
zenohd: install
	@v=$$($(BIN)/python -c 'from importlib.metadata import version; print(version("eclipse-zenoh"))'); \
	root="$(ZENOHD_ROOT)"; \
	if [ -x "$$root/bin/zenohd" ]; then echo "zenohd $$v: $$root/bin/zenohd"; \
	elif ! command -v cargo >/dev/null 2>&1; then \
	  echo "no cargo: zenohd $$v not built; tests/deploy/test_zenohd.py will be skipped"; \
	else echo "building zenohd $$v into $$root (cargo install)"; \
	  cargo install --quiet --locked --root "$$root" zenohd --version "$$v" \
	  || echo "cargo install zenohd $$v failed; tests/deploy/test_zenohd.py will be skipped"; \
	fi

bench: install
	$(BIN)/telerobot bench --quick

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache artifacts
