# conformd — `make demo` runs the main job on built-in defaults, `make test` runs every
# test. Both first install the system packages the build needs when they are missing.

# fonts-dejavu-core: the plots' font (a copy is built into the binary for machines
# without it); libjs-three: the capture page's 3D view (three.js served from
# /usr/share/javascript/three)
APT_PACKAGES := libopencv-dev clang libclang-dev pkg-config libudev-dev fonts-dejavu-core libjs-three
# `make deb`: dpkg-shlibdeps (dpkg-dev), strip (binutils), the manual page (help2man),
# and lintian to check the package
DEB_PACKAGES := dpkg-dev binutils help2man lintian
# the trigger box's firmware (firmware/trigger-box) and the emulator it is tested in
# (firmware/sim: simavr)
FIRMWARE_PACKAGES := gcc-avr avr-libc binutils-avr libsimavr-dev
# the status page's browser test runs Debian's headless Chromium; the journal and worker
# tests start throwaway PostgreSQL clusters with Debian's server; the package's test
# builds and checks the package (DEB_PACKAGES), installs it into a throwaway root
# (fakeroot when not root) and verifies its units (systemd-analyze); the firmware's
# tests build it and run it in simavr (FIRMWARE_PACKAGES)
TEST_PACKAGES := chromium chromium-driver postgresql $(DEB_PACKAGES) fakeroot systemd \
	$(FIRMWARE_PACKAGES)
CARGO ?= cargo
DEMO_OUT ?= demo-output

.PHONY: all deps test-deps apt build lint test test-hardware verify-unit demo bench deb firmware clean

all: build

# System packages through apt-get (sudo when not root); the Rust toolchain must exist.
deps:
	@$(MAKE) --no-print-directory apt PACKAGES="$(APT_PACKAGES)"
	@command -v $(CARGO) >/dev/null || { echo "cargo is not installed: install the Rust toolchain with rustup"; exit 1; }

test-deps: deps
	@$(MAKE) --no-print-directory apt PACKAGES="$(TEST_PACKAGES)"

apt:
	@missing=""; \
	for p in $(PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	fi

build: deps
	$(CARGO) build --locked --release

# conformd's own code is compiled by clippy's driver: rustc with clippy's lints added
# (warnings are errors), so one compile both lints and builds. `cargo clippy` would check
# every dependency a second time, in check mode, before the build compiled them (about
# four minutes of a fresh run on two cores). The driver leaves the dependencies to rustc
# and turns off only rustc's MIR optimisations in our crates; LLVM optimises as before (the
# harder development set: 47-53 s built either way). `make build`, `make deb` and
# `make demo` compile with rustc alone. Every cargo command of `make test` runs with these
# set, as the build's fingerprints include them (a cargo command without them rebuilds
# conformd's own crates, not the dependencies).
CLIPPY_DRIVER := $(shell command -v clippy-driver 2>/dev/null)
LINTED := RUSTC_WORKSPACE_WRAPPER=$(CLIPPY_DRIVER) CLIPPY_ARGS=-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__

# Formatting, then every target built and linted: the library, the binary, the unit and
# integration tests, the benchmarks. What the tests run is what ships: no feature or
# hook of the tests is compiled into the program (the tests stand in through its
# configuration, e.g. `[worker] program`).
lint: deps
	@[ -n "$(CLIPPY_DRIVER)" ] || { echo "clippy is not installed: rustup component add clippy"; exit 1; }
	$(CARGO) fmt --all --check
	$(LINTED) $(CARGO) build --locked --profile ci --all-targets

# Lint, then every test, compiled once: the `ci` profile optimises (the known-answer
# tests are heavy) and keeps debug assertions and overflow checks on.
# The whole run has a limit (compiling included): a test that hangs where no deadline
# of its own catches it stops the run with a line saying so, rather than the CI job's
# own limit ending it without one.
TEST_LIMIT_S ?= 2700
test: test-deps lint
	@$(LINTED) timeout --kill-after=60 $(TEST_LIMIT_S) $(CARGO) test --locked --profile ci; rc=$$?; \
	if [ $$rc -eq 124 ] || [ $$rc -eq 137 ]; then echo "make test: stopped after $(TEST_LIMIT_S) s (TEST_LIMIT_S): a test hung"; fi; \
	exit $$rc
	@$(MAKE) --no-print-directory verify-unit

# systemd-analyze verify on the units (where systemd is), pointing at the binary just built.
verify-unit:
	@if command -v systemd-analyze >/dev/null; then \
	  d=$$(mktemp -d); rc=0; \
	  for u in conformd conformd-worker; do \
	    sed "s#/usr/local/bin/conformd#$(CURDIR)/target/ci/conformd#" systemd/$$u.service > $$d/$$u.service; \
	    systemd-analyze verify $$d/$$u.service && echo "systemd unit $$u verified" || rc=1; \
	  done; \
	  rm -rf $$d; exit $$rc; \
	else echo "skipped: systemd units not verified (systemd-analyze not found)"; fi

# On a station with cameras: the test that needs a real V4L2 device (ignored by `test`).
test-hardware: deps
	$(LINTED) $(CARGO) test --locked --profile ci --test all v4l2_hardware:: -- --ignored

# The Debian package of the release build (packaging/deb/build.sh), checked by lintian:
# target/debian/conformd_<version>-1_<arch>.deb, installed with `apt install ./...deb`.
deb: deps
	@$(MAKE) --no-print-directory apt PACKAGES="$(DEB_PACKAGES)"
	$(CARGO) build --locked --release
	@deb=$$(sh packaging/deb/build.sh target/release/conformd target/debian) && \
	lintian --fail-on error "$$deb" && echo "built $$deb (lintian: no errors)"

# The trigger box's firmware (build/trigger-box.hex for avrdude: README, "The reference
# trigger box") and its emulator harness (firmware/sim/build/boxsim).
firmware:
	@$(MAKE) --no-print-directory apt PACKAGES="$(FIRMWARE_PACKAGES)"
	$(MAKE) -C firmware

demo: deps
	$(CARGO) run --locked --release -- demo --out $(DEMO_OUT)

bench: test-deps
	$(CARGO) bench --locked --bench conform
	$(CARGO) bench --locked --bench model
	$(CARGO) bench --locked --bench stereo
	$(CARGO) bench --locked --bench stereo_real
	$(CARGO) bench --locked --bench daemon
	$(CARGO) bench --locked --bench journal

clean:
	$(CARGO) clean
	$(MAKE) -C firmware clean
	rm -rf $(DEMO_OUT)
